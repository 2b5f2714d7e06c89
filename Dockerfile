# The viewer's OpenSeadragon comes from the npm registry (pinned in package-lock.json); setup.py's build hook
# copies it into the wheel (api/static/vendor/openseadragon), so the image serves the viewer from the package.
FROM node:20-slim AS viewer
WORKDIR /app
COPY package.json package-lock.json ./
RUN npm ci --no-audit --no-fund

FROM python:3.11-slim
WORKDIR /build
COPY pyproject.toml constraints.txt setup.py MANIFEST.in README.md package.json package-lock.json ./
COPY services services
COPY api api
COPY cli cli
COPY workers workers
COPY --from=viewer /app/node_modules/openseadragon node_modules/openseadragon
RUN pip install --no-cache-dir -c constraints.txt . && rm -rf /build
# the service runs as an unprivileged user: it owns /data (a new volume mounted there takes this ownership) and
# nothing else it could write
RUN useradd --system --uid 10001 --user-group --home-dir /app --shell /usr/sbin/nologin veinmosaic \
    && mkdir -p /app /data && chown veinmosaic:veinmosaic /data
WORKDIR /app
USER veinmosaic
ENV VEINMOSAIC_DATA_DIR=/data
EXPOSE 8000
CMD ["veinmosaic", "serve", "--host", "0.0.0.0"]
