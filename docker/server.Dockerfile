# Map server image: `wardmap server` (and `wardmap router`, the same image with another command).
# Build from the repository root:  docker build -f docker/server.Dockerfile -t wardmap-server .
# No model or data is downloaded at build or run time; the trained segmentation model ships
# inside the package (server/models/).
FROM python:3.11.7-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

RUN useradd --system --create-home --home-dir /var/lib/wardmap --uid 10001 wardmap \
    && mkdir -p /etc/wardmap/tls && chown wardmap /etc/wardmap/tls  # the TLS volume (deploy/compose.yaml)

WORKDIR /opt/wardmap
COPY pyproject.toml README.md ./
COPY cli ./cli
COPY edge ./edge
COPY server ./server
COPY shared ./shared
COPY sim ./sim
RUN pip install --no-compile . && rm -rf /opt/wardmap/build

USER wardmap
WORKDIR /var/lib/wardmap
VOLUME ["/var/lib/wardmap"]
EXPOSE 8080
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import urllib.request,sys; urllib.request.urlopen('http://127.0.0.1:8080/healthz', timeout=4); sys.exit(0)"]
ENTRYPOINT ["wardmap"]
CMD ["server", "--connect", "tcp/router:7447", "--db", "sqlite:////var/lib/wardmap/wardmap.db", "--http", "0.0.0.0:8080"]
