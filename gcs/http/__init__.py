"""The HTTP API: ``app.py`` composes one router per resource (``routes/``) over narrow ports
(``ports.py``, handed to routes by ``deps.py``), behind the guard (``guard.py``); ``models.py`` are
the pydantic models shared with the client. See docs/api.md.

The package itself imports nothing: the command-line client (``client.py``, every ``gcs`` command)
needs only ``models.py``, and importing the app (FastAPI, the routes) would add about a second to
each command's start."""
