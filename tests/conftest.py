import os
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
# The project's packages, and the helpers beside this file (prerequisites, twin_checks) for the tests in the folders
# below it, which follow the code they test (pipeline/, stages/, plenoxels/, bench/).
sys.path[:0] = [str(REPO), str(TESTS)]
os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count() or 2))
