# sdh2svc: the service on the embedded simulated hand, exposed with a token.
#
#   docker build -t sdh2svc .
#   docker run -p 8000:8000 -p 8080:8080 -e SDH2SVC_SERVICE__TOKEN=$(openssl rand -hex 16) sdh2svc
#
# A real hand instead: pass its two serial lines through and point the service at them, e.g.
#   docker run --device /dev/ttyUSB0 --device /dev/ttyUSB1 -p 8000:8000 -p 8080:8080 \
#     -e SDH2SVC_SERVICE__TOKEN=… sdh2svc .venv/bin/sdh2svc serve --sdh /dev/ttyUSB0 --dsa /dev/ttyUSB1
# (tests/test_container.py runs these steps and this command in a fresh virtual environment)
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY sdh2svc ./sdh2svc
COPY config ./config
COPY web ./web
RUN python3 -m venv .venv && .venv/bin/pip install --no-cache-dir .
ENV SDH2SVC_SERVICE__HOST=0.0.0.0 SDH2SVC_STORAGE__DB_PATH=/data/runs.sqlite
VOLUME /data
EXPOSE 8000 8080
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s CMD [".venv/bin/sdh2svc", "health"]
CMD [".venv/bin/sdh2svc", "serve", "--sim"]
