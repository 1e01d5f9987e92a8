"""The library surface: every exported name resolves, importing it stays lean, and the analysis
side works on a machine without matplotlib (reports are the only layer that needs it)."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

import dt_runtime


@pytest.mark.parametrize("name", dt_runtime.__all__)
def test_every_exported_name_resolves(name):
    assert getattr(dt_runtime, name) is not None


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        dt_runtime.nope  # noqa: B018


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=120)


def test_the_documented_import_line_loads_no_daemon_driver_or_plotting():
    p = _run("""
        import sys
        from dt_runtime import HybridModel, MultiOutputGP, Twin, read_table, diagnose, compare
        heavy = sorted({m.split('.')[0] for m in sys.modules} & {'matplotlib', 'zenoh', 'pybullet', 'cv2', 'serial'})
        print(','.join(heavy))
    """)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == ""


def test_analysis_imports_without_matplotlib():
    # A finder that refuses matplotlib stands in for a machine without it.
    p = _run("""
        import sys
        class NoMpl:
            def find_spec(self, name, path=None, target=None):
                if name.split('.')[0] == 'matplotlib':
                    raise ImportError('matplotlib is not installed here')
        sys.meta_path.insert(0, NoMpl())
        import dt_runtime.analysis.compare, dt_runtime.analysis.diagnose, dt_runtime.models.hybrid
        print('ok')
    """)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "ok"
