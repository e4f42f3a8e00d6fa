"""WSGI entry point for production servers: ``waitress-serve study_site.wsgi:app`` or
``gunicorn 'study_site.wsgi:app'``. Configuration comes from ``CAMO_STUDY_<KEY>`` environment
variables (at least ``CAMO_STUDY_STIMULI_DIR`` and ``CAMO_STUDY_DATABASE_URL``)."""

from . import create_app
from .config import from_env

app = create_app(from_env())
