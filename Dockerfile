# One image for the server (viewer included) and the simulated clients.
FROM python:3.11-slim

RUN apt-get update && apt-get install -y --no-install-recommends nodejs npm libhidapi-hidraw0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md haptic_cli.py haptic_demo.py ./
COPY shared ./shared
COPY server ./server
COPY client ./client
RUN pip install --no-cache-dir .
COPY web ./web
RUN cd web && npm ci --no-audit --no-fund

EXPOSE 8765
ENTRYPOINT ["haptic"]
# Off loopback the server requires tokens: mount a token file (lines "TOKEN ROLE [NAME]"), e.g.
#   docker run -v $PWD/tokens.txt:/run/secrets/haptic_tokens:ro -p 8765:8765 haptic-collab
# and open http://localhost:8765/#token=... (docs/security.md; add TLS on a real network).
CMD ["server", "--host", "0.0.0.0", "--port", "8765", "--token-file", "/run/secrets/haptic_tokens"]
