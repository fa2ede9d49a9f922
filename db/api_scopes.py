"""The scopes of the HTTP API's bearer keys (a module of its own: the command line names them
without loading the ORM).

`read` (GET), `submit` (uploads and jobs; implies read), `admin` (implies all).
"""

API_SCOPES: tuple[str, ...] = ("read", "submit", "admin")
