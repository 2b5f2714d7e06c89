# The viewer's OpenSeadragon comes from the npm registry (pinned in package-lock.json).
FROM node:20-slim AS viewer
WORKDIR /app
COPY package.json package-lock.json ./
RUN npm ci --no-audit --no-fund

FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY services services
COPY api api
COPY workers workers
RUN pip install --no-cache-dir .
COPY --from=viewer /app/node_modules node_modules
ENV VEINMOSAIC_DATA_DIR=/data \
    VEINMOSAIC_VIEWER_ASSETS_DIR=/app/node_modules/openseadragon/build/openseadragon
EXPOSE 8000
CMD ["veinmosaic", "serve", "--host", "0.0.0.0"]
