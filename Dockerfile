# One image for the server (viewer included) and the simulated clients.
# Stage 1 builds the wheel: node and npm only to take three.js from web/package-lock.json, which the
# wheel carries as package data. Stage 2 installs that wheel: no node, no npm, no source tree.
FROM python:3.11-slim AS build
RUN apt-get update && apt-get install -y --no-install-recommends nodejs npm \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY pyproject.toml README.md ./
COPY haptic_collab ./haptic_collab
COPY shared ./shared
COPY server ./server
COPY client ./client
COPY web ./web
RUN cd web && npm ci --no-audit --no-fund
RUN pip wheel --no-cache-dir --no-deps -w /dist .

FROM python:3.11-slim
RUN apt-get update && apt-get install -y --no-install-recommends libhidapi-hidraw0 \
    && rm -rf /var/lib/apt/lists/*
COPY --from=build /dist /dist
RUN pip install --no-cache-dir /dist/haptic_collab-*.whl && rm -rf /dist \
    && useradd --uid 10001 --user-group --create-home --home-dir /home/haptic \
       --shell /usr/sbin/nologin haptic \
    && mkdir -p /var/lib/haptic/snapshots && chown -R 10001:10001 /var/lib/haptic
# One BLAS / OpenMP thread per process: the simulation, its gain design worker and the clients
# are processes of their own already, and a thread pool per process would fight them for the
# same cores (a Kubernetes pod gets a CPU request, not a machine).
ENV OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMEXPR_NUM_THREADS=1 \
    PYTHONUNBUFFERED=1
# Not root; numeric, so that Kubernetes' runAsNonRoot can verify it.
USER 10001:10001
WORKDIR /home/haptic

# 8765: a room server (haptic server); 8780: the lobby (haptic lobby)
EXPOSE 8765 8780
ENTRYPOINT ["haptic"]
# Off loopback the server requires tokens: mount a token file (lines "TOKEN ROLE [NAME]"), e.g.
#   docker run -v $PWD/tokens.txt:/run/secrets/haptic_tokens:ro -p 8765:8765 haptic-collab
# and open http://localhost:8765/#token=... (docs/security.md; add TLS on a real network).
CMD ["server", "--host", "0.0.0.0", "--port", "8765", "--token-file", "/run/secrets/haptic_tokens"]
