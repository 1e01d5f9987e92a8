"""Where the project's shipped configs and data live (a fresh clone needs nothing else)."""
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
DATA = ROOT / "dt_runtime" / "data"
