#!/bin/sh
# tests/integration/test_vcan_harness.py, what a script sees (run by the vcan harness with
# /bin/sh): its working directory, environment (VCAN_TEST_TOKEN) and tools; Python with the
# project's heavy imports and 256 MiB more (memory), /dev/shm (multiprocessing); stderr; exit
# status 3.

echo "cwd=$(pwd)"
echo "token=$VCAN_TEST_TOKEN"
echo "python=$(command -v python)"
for tool in sim-ecu motor-monitor; do
  if command -v "$tool" >/dev/null; then echo "$tool=found"; else echo "$tool=missing"; fi
done
python - <<'PY'
import numpy, scipy.linalg, scipy.signal, numba, rerun, can
from multiprocessing import shared_memory
shm = shared_memory.SharedMemory(create=True, size=1 << 20)
shm.close()
shm.unlink()
block = numpy.ones((4096, 8192))  # 256 MiB on top of ~200 MiB of imports (slow in UML)
print("numpy_sum=%d" % block.sum())
PY
echo "python_rc=$?"
echo "to stderr" >&2
exit 3
