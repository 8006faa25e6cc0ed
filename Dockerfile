# Edge image of the spindle thermal-error gateway.
# Slim Python base, dependencies pinned by pyproject.toml, runs as a non-root user.
#
#   docker build -t spindle-thermal-gateway:0.1.0 .        (from the repository root)
#   deploy/docker-compose.yml builds and runs it with InfluxDB and Grafana (deploy/README.md).
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MPLCONFIGDIR=/tmp/matplotlib

# A fixed uid/gid, so a bind-mounted /data can be chowned to it (chown -R 10001:10001 DIR).
RUN groupadd --system --gid 10001 gateway \
    && useradd --system --uid 10001 --gid gateway --home-dir /srv/gateway --shell /usr/sbin/nologin gateway

WORKDIR /srv/gateway

# Dependencies first (their layer is reused while only the code changes): the pins of
# pyproject.toml, read from the file itself so there is one list to keep.
COPY pyproject.toml README.md ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" \
        > /tmp/requirements.txt \
    && pip install --no-cache-dir -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt

# The package itself. The source tree stays in the working directory: `python -m` puts it
# first on sys.path, and it carries the data files setuptools does not install
# (simulator/*.yaml).
COPY gateway ./gateway
COPY drivers ./drivers
COPY models ./models
COPY simulator ./simulator
RUN pip install --no-cache-dir --no-deps . \
    && mkdir -p /data/state /data/models /config \
    && chown -R gateway:gateway /data /config

# An example configuration (edit or mount your own) and the bundled measured runs
# (data/fl_thermal.csv), e.g. to try `fit` inside the container.
COPY --chown=gateway:gateway deploy/config.docker.yaml /config/config.yaml
COPY --chown=gateway:gateway data ./data

# Configuration, and the model store / state / logged data, live outside the image.
VOLUME ["/config", "/data"]
USER gateway

# Healthy while every machine loop has written a heartbeat in the last 30 s
# (gateway/health.py; state_dir /data/state in the configuration).
HEALTHCHECK --interval=15s --timeout=10s --start-period=60s --retries=3 \
    CMD ["python", "-m", "gateway.health", "--state-dir", "/data/state", "--max-age-s", "30"]

STOPSIGNAL SIGTERM
ENTRYPOINT ["python", "-m", "gateway"]
CMD ["run", "--config", "/config/config.yaml"]
