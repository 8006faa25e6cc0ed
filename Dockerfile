# Edge image of the spindle thermal-error gateway.
# Slim Python base, dependencies pinned by pyproject.toml, runs as a non-root user.
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1

RUN groupadd --system gateway && useradd --system --gid gateway --home-dir /srv/gateway gateway

WORKDIR /srv/gateway
COPY pyproject.toml README.md ./
COPY gateway ./gateway
COPY drivers ./drivers
COPY models ./models
RUN pip install --no-cache-dir . && mkdir -p /data /config && chown gateway:gateway /data /config

COPY --chown=gateway:gateway config.yaml /config/config.yaml
COPY --chown=gateway:gateway data ./data

# Configuration and the model store / logged data live outside the image.
VOLUME ["/config", "/data"]
USER gateway

ENTRYPOINT ["python", "-m", "gateway"]
CMD ["--help"]
