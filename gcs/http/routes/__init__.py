"""One ``APIRouter`` per resource of the HTTP API; gcs/http/app.py includes them in order."""
