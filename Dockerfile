# citytherm: one image for the HTTP API (`citytherm serve`), the Celery workers (`citytherm worker`)
# and one-shot commands (`citytherm db upgrade`, `citytherm import ...`); see docker-compose.yml.
#   docker build -t citytherm .
#   docker run --rm citytherm --help
# The /viewer page's three.js modules (docs/viewer.md): installed from the npm registry by the lock
# file of tools/viewer/ in a node stage, and copied into the package before it is installed; the
# image serves them itself (no CDN, no node at run time).
FROM node:20-bookworm-slim AS viewer
WORKDIR /viewer
COPY tools/viewer/package.json tools/viewer/package-lock.json tools/viewer/vendor.mjs ./
RUN npm ci --omit=dev --no-audit --no-fund && node vendor.mjs /viewer/vendor

FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_ROOT_USER_ACTION=ignore

# Shared libraries open3d-cpu and opencv load at import (as .ci/system-deps.sh installs them for CI).
RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 libgl1 libglib2.0-0 \
 && rm -rf /var/lib/apt/lists/*

# The dependencies first, in a layer of their own (read from pyproject.toml with tomllib), so that
# a change to the code does not download and install them again.
COPY pyproject.toml /tmp/citytherm-deps/pyproject.toml
RUN python -c "import tomllib; d = tomllib.load(open('/tmp/citytherm-deps/pyproject.toml', 'rb')); print(*d['project']['dependencies'], sep=chr(10))" \
        > /tmp/citytherm-deps/requirements.txt \
 && pip install -r /tmp/citytherm-deps/requirements.txt \
 && rm -rf /tmp/citytherm-deps

# The project itself with the viewer's modules (not editable, no dev extra); the sources are not kept
# in the image. gcc builds the compiled CityGML walk (setup.py; the image has Python's headers) and
# is removed again in the same layer.
COPY . /src
COPY --from=viewer /viewer/vendor /src/services/api/viewer/vendor
RUN apt-get update \
 && apt-get install -y --no-install-recommends gcc libc6-dev \
 && pip install /src && rm -rf /src \
 && python -c "from db.citygml.building_read import COMPILED_WALK; from db.import_rows import _fmt; assert COMPILED_WALK and _fmt" \
 && apt-get purge -y --auto-remove gcc libc6-dev \
 && rm -rf /var/lib/apt/lists/*

# A non-root user; /data (CITYTHERM_STORAGE_DIR) belongs to it, and a new named volume mounted
# there takes this ownership, so the API and the workers can write to it.
RUN groupadd --system --gid 10001 citytherm \
 && useradd --system --uid 10001 --gid citytherm --home-dir /home/citytherm --create-home \
        --shell /usr/sbin/nologin citytherm \
 && mkdir -p /data /app \
 && chown citytherm:citytherm /data /app

ENV CITYTHERM_STORAGE_DIR=/data
WORKDIR /app
USER 10001:10001
EXPOSE 8000

ENTRYPOINT ["citytherm"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8000"]
