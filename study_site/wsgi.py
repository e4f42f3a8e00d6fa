"""WSGI entry point for production servers: ``waitress-serve study_site.wsgi:app`` or
``gunicorn 'study_site.wsgi:app'``. Configuration comes from ``CAMO_STUDY_<KEY>`` environment
variables (at least ``CAMO_STUDY_STIMULI_DIR``, ``CAMO_STUDY_DATABASE_URL`` and the participant-id key,
``CAMO_STUDY_ID_HMAC_KEY_FILE`` from ``camo study make-key FILE`` or ``CAMO_STUDY_ID_HMAC_KEY``)."""

from study_site import create_app
from study_site.config import from_env

app = create_app(from_env())
