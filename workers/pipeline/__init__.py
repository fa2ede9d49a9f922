"""The photogrammetry core of citytherm.

Pure computation over numpy arrays and small immutable dataclasses: no Celery, SQLAlchemy or
FastAPI imports, no network or database I/O. Both the command line (`services/`) and the Celery
tasks (`workers/`) call it. One module per stage; each module docstring says what goes in and
what comes out.
"""
