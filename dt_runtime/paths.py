"""Where the project's shipped configs and data live (a fresh clone needs nothing else)."""
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
DATA = Path(__file__).resolve().parent / "data"
