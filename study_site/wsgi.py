"""WSGI entry point for production servers: ``gunicorn -w 3 -k gthread --threads 8 'study_site.wsgi:app'`` (what
``camo study serve --workers 3`` runs) or ``waitress-serve study_site.wsgi:app``. Configuration comes from
``CAMO_STUDY_<KEY>`` environment variables: at least ``CAMO_STUDY_STIMULI_DIR``, ``CAMO_STUDY_DATABASE_URL``, the
participant-id key (``CAMO_STUDY_ID_HMAC_KEY_FILE``) and the cookie-signing key (``CAMO_STUDY_SECRET_KEY_FILE``),
each made by ``camo study make-key FILE``."""

from study_site import create_app
from study_site.config import from_env

app = create_app(from_env())
