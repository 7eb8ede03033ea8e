import sys
from pathlib import Path

# helpers importable from tests; fluxdrive from the repo even without an editable install
sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "python"))
