"""Test-session settings shared by every test module."""

import os

# Same single-threaded BLAS as the product (see backend/cli.py): before numpy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
