# Edge agent image: `wardmap edge` on a robot (x86_64 or aarch64, e.g. a Jetson TX2 class board).
# Build from the repository root:  docker build -f docker/edge.Dockerfile -t wardmap-edge .
# The outbox lives on the volume /var/lib/wardmap so keyframes survive a container restart.
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
COPY deploy/edge.toml /etc/wardmap/edge.toml
RUN pip install --no-compile . && rm -rf /opt/wardmap/build

USER wardmap
WORKDIR /var/lib/wardmap
VOLUME ["/var/lib/wardmap"]
# SIGTERM flushes the outbox and exits cleanly (docker stop); give it the flush timeout.
STOPSIGNAL SIGTERM
ENTRYPOINT ["wardmap"]
CMD ["edge", "--robot", "robot_0", "--source", "sim:aisle_slow_1", "--connect", "tcp/router:7447", "--outbox", "/var/lib/wardmap/outbox", "--rate", "10", "--config", "/etc/wardmap/edge.toml"]
