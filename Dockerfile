# Edge image of the spindle thermal-error gateway.
# Python 3.11 on Debian bookworm, the locked dependency set, runs as a non-root user.
#
#   scripts/build-wheelhouse.sh                                # the wheels, once per lock
#   docker build -t spindle-thermal-gateway:0.1.0 .           (from the repository root)
#   deploy/docker-compose.yml builds and runs it with InfluxDB and Grafana (deploy/README.md).
#
# The build needs no package index: every dependency is installed from wheelhouse/ (made
# on a connected machine by scripts/build-wheelhouse.sh from requirements.lock, hashes
# checked), which is how an air-gapped plant builds it. BASE is any image with Python 3.11
# (python3, its venv module) on glibc ≥ 2.36; scripts/build-image.sh builds one from
# Debian packages when no registry is reachable.
ARG BASE=python:3.11-slim-bookworm

# --- the dependencies, installed into /opt/venv from the wheelhouse -------------------------
FROM ${BASE} AS dependencies
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
COPY requirements.lock /tmp/requirements.lock
COPY wheelhouse /tmp/wheelhouse
RUN python3 -m venv /opt/venv \
    && /opt/venv/bin/pip install --no-index --find-links /tmp/wheelhouse \
        --require-hashes --only-binary=:all: -r /tmp/requirements.lock
# The package itself, for its metadata and entry point (build backend from the wheelhouse),
# beside the venv in /opt/package (same layout): the venv's large layer then changes only
# with requirements.lock, and a code change rebuilds only the package's few files.
COPY pyproject.toml README.md /tmp/src/
COPY gateway /tmp/src/gateway
COPY drivers /tmp/src/drivers
COPY models /tmp/src/models
COPY simulator /tmp/src/simulator
RUN /opt/venv/bin/pip install --no-index --find-links /tmp/wheelhouse --no-deps --no-compile \
        --prefix /opt/package /tmp/src

# --- the image --------------------------------------------------------------------------------
FROM ${BASE}
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    MPLCONFIGDIR=/tmp/matplotlib \
    SPINDLE_MODEL_KEY_FILE=/data/keys/model-signing.key

# A fixed uid/gid, so a bind-mounted /data can be chowned to it (chown -R 10001:10001 DIR).
RUN groupadd --system --gid 10001 gateway \
    && useradd --system --uid 10001 --gid gateway --home-dir /srv/gateway --shell /usr/sbin/nologin gateway

COPY --from=dependencies /opt/venv /opt/venv
COPY --from=dependencies /opt/package /opt/venv
WORKDIR /srv/gateway

# The source tree stays in the working directory: `python -m` puts it first on sys.path,
# and it carries the data files setuptools does not install (simulator/*.yaml).
COPY gateway ./gateway
COPY drivers ./drivers
COPY models ./models
COPY simulator ./simulator
# The model signing key (models/signing.py): made by the first `fit` or `models sign` in the
# persisted /data volume, outside every model store (/data/models/...), mode 600.
# Compiled once here, so a read-only root needs no __pycache__ at run time.
RUN python -m compileall -q gateway drivers models simulator /opt/venv/lib \
    && mkdir -p /data/state /data/models /data/keys /config \
    && chown -R gateway:gateway /data /config \
    && chmod 700 /data/keys

# An example configuration (edit or mount your own) and the bundled measured runs
# (data/fl_thermal.csv), e.g. to try `fit` inside the container.
COPY --chown=gateway:gateway deploy/config.docker.yaml /config/config.yaml
COPY --chown=gateway:gateway data ./data

# Configuration, and the model store / state / logged data, live outside the image.
VOLUME ["/config", "/data"]
USER gateway

# Healthy while every machine loop has written a heartbeat in the last 30 s
# (gateway/outputs/heartbeat.py; state_dir /data/state in the configuration).
HEALTHCHECK --interval=15s --timeout=10s --start-period=60s --retries=3 \
    CMD ["python", "-m", "gateway.outputs.heartbeat", "--state-dir", "/data/state", "--max-age-s", "30"]

STOPSIGNAL SIGTERM
ENTRYPOINT ["python", "-m", "gateway"]
CMD ["run", "--config", "/config/config.yaml"]
