# ShadowCorr inference service.  CPU image by default:
#   docker build -t shadowcorr .
# CUDA variant (torch from a CUDA wheel index; run with --gpus all and SHADOWCORR_DEVICE=cuda):
#   docker build --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cu124 -t shadowcorr:cuda .
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
WORKDIR /src
COPY pyproject.toml README.md CHANGELOG.md ./
COPY scripts/install-runtime.sh scripts/
COPY shadowcorr shadowcorr
COPY service service
COPY clients clients
COPY batch batch
# The package data carries the default model (shadowcorr/models/default.safetensors).
RUN TORCH_INDEX_URL="${TORCH_INDEX_URL}" bash scripts/install-runtime.sh /opt/venv

FROM ${PYTHON_IMAGE} AS runtime
ARG VERSION=0.1.0
LABEL org.opencontainers.image.title="shadowcorr" \
      org.opencontainers.image.description="Multi-view 3D segment correspondence (ShadowCorr) inference service" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.licenses="MIT"
RUN groupadd --system --gid 10001 shadowcorr \
 && useradd --system --uid 10001 --gid 10001 --no-create-home --shell /usr/sbin/nologin shadowcorr
COPY --from=build /opt/venv /opt/venv
# Configuration comes only from SHADOWCORR_* environment variables (see the README).
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    SHADOWCORR_HOST=0.0.0.0 \
    SHADOWCORR_PORT=8000 \
    SHADOWCORR_GRACEFUL_SHUTDOWN_S=30
USER 10001:10001
EXPOSE 8000
# /health answers 503 until the model is loaded and warmed up; start-period covers that.
HEALTHCHECK --interval=15s --timeout=5s --start-period=90s --retries=3 \
  CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/health' % os.environ.get('SHADOWCORR_PORT', '8000'), timeout=4)"]
# SIGTERM starts a graceful drain of at most SHADOWCORR_GRACEFUL_SHUTDOWN_S seconds;
# give the container a stop timeout a little longer (docker run --stop-timeout 35,
# compose stop_grace_period: 35s).
STOPSIGNAL SIGTERM
ENTRYPOINT ["shadowcorr"]
CMD ["serve"]
