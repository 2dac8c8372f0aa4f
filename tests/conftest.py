"""Suite-wide setup: subprocesses started by tests (`python -m hil ...`) import this checkout."""

import os
from pathlib import Path

REPO_ROOT = str(Path(__file__).resolve().parents[1])
os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (REPO_ROOT, os.environ.get("PYTHONPATH")) if p)
