"""The HTTP API of the citytherm service (FastAPI): `create_app(settings)`."""

from services.api.app import create_app

__all__ = ["create_app"]
