# floornav daemon image. No engine is needed to read this; `scripts/check-deploy` lints it.
#
#   docker build -t floornav .
#   # simulator (the shipped config.toml):
#   docker run --rm -p 8080:8080 floornav
#   # real robot: pass the devices, select them by environment (FLOORNAV_<SECTION>__<KEY>):
#   docker run --rm -p 8080:8080 \
#     --device /dev/ttyACM0 --device /dev/video0 \
#     -e FLOORNAV_CAMERA__SOURCE=device -e FLOORNAV_CAMERA__DEVICE=/dev/video0 \
#     -e FLOORNAV_SERIAL__BACKEND=port -e FLOORNAV_SERIAL__PORT=/dev/ttyACM0 \
#     -e FLOORNAV_RUNTIME__AUTOSTART=false \
#     -v floornav-state:/var/lib/floornav floornav
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/var/cache/floornav/numba \
    FLOORNAV_WEB__HOST=0.0.0.0 \
    FLOORNAV_WEB__PORT=8080 \
    FLOORNAV_MAPPING__FLOOR_CALIBRATION_FILE=/var/lib/floornav/floor.json

# dialout owns /dev/ttyACM* and video owns /dev/video* on Debian hosts (GIDs 20 and 44,
# the same in this Debian-based image), so devices passed with --device just work.
RUN groupadd --system floornav \
    && useradd --system --gid floornav --groups dialout,video \
       --home-dir /home/floornav --create-home --shell /usr/sbin/nologin floornav \
    && mkdir -p /var/lib/floornav /var/cache/floornav/numba \
    && chown -R floornav:floornav /var/lib/floornav /var/cache/floornav

WORKDIR /opt/floornav

# Dependencies and the package first, so editing the dashboard does not reinstall them.
COPY pyproject.toml README.md ./
COPY app ./app
RUN pip install --no-cache-dir .

# The daemon reads config.toml and serves static/ from its working directory.
COPY config.toml ./
COPY static ./static

# numba's kernels compiled into the image's cache (NUMBA_CACHE_DIR), so the daemon loads
# them at start instead of compiling for seconds; handed to the user who must read them
# and, on a host with another CPU model (numba keys the cache by it), add its own.
RUN floornav warmup --config /opt/floornav/config.toml \
    && chown -R floornav:floornav /var/cache/floornav

USER floornav

EXPOSE 8080

# /api/status answers whenever the event loop runs; the daemon serves once its numba
# kernels are ready (seconds to recompile on another CPU), hence the long start period.
HEALTHCHECK --interval=15s --timeout=5s --start-period=90s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/api/status' % os.environ.get('FLOORNAV_WEB__PORT', '8080'), timeout=4)"]

STOPSIGNAL SIGTERM
CMD ["floornav", "run", "--config", "/opt/floornav/config.toml"]
