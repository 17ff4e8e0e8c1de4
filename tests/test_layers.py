"""The layers hold: no import runs up (lckit <- lcsim <- lcdata <- lcmodels <- lccli <- tools, experiments), no
two modules import each other in a circle, no private name crosses a package (``tools/import_graph.py``)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_no_upward_import_no_circle_no_private_name_across_packages():
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "import_graph.py"), "--check"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "upward arrows: 0" in done.stdout and "circles: 0" in done.stdout
    assert "lcmodels     -> lcsim" in done.stdout  # it did read the imports
