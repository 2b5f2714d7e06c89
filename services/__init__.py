"""veinmosaic's domain: the algorithm, the simulator, and the storage and queue adapters (no web code)."""

import os
import sys

# OpenCV reads its per-decode pixel limit once, when the library loads, so it is set here, before any module of
# the project imports cv2. 2**26 px (64 Mpx) is a backstop against decompression bombs far above any frame
# (frames are checked against the much smaller max_frame_side from their header first, see image_header.py)
# yet above any mosaic the service decodes (a 400 mm canvas at 8 px/mm is 10 Mpx). An operator's value wins.
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(1 << 26))

# One BLAS thread per process. The matrix products here are small (descriptor distances, 500 x 500 x 128) and the
# parallelism is across processes (workers) and the prepare thread pool; OpenBLAS's own threads busy-wait for work,
# and with several workers on a 2-core machine they took the CPU from each other: descriptor matching cost 4.7x
# and a worker's per-frame CPU 1.6x (bench/worker_cost.py). An operator's value wins. The variable is read when a
# BLAS library loads: where numpy came first (cv2 loads it: `python -m workers.main` imports cv2 before this
# package, as docker-compose.yml starts the workers; a bench that imports numpy first), the loaded BLAS is limited
# here at run time instead (threadpoolctl): `python bench/accuracy.py --no-sim --methods best`, which imports numpy
# first, took 0.039-0.045 s a frame on the shared scans without this and 0.026-0.032 with it.
_BLAS_THREADS = os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if "numpy" in sys.modules and _BLAS_THREADS.isdigit():
    from threadpoolctl import threadpool_limits

    threadpool_limits(int(_BLAS_THREADS), user_api="blas")
