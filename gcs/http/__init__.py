"""The HTTP API: ``app.py`` composes one router per resource (``routes/``) over narrow ports
(``ports.py``, handed to routes by ``deps.py``), behind the guard (``guard.py``); ``models.py`` are
the pydantic models shared with the client. See docs/api.md."""

from gcs.http.app import create_app

__all__ = ["create_app"]
