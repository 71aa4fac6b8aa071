"""The numerical core stays free of I/O libraries."""

import subprocess
import sys


def test_core_does_not_import_can_or_cantools():
    code = (
        "import sys, online_id.core.identification, online_id.core.rels, online_id.core.pem, "
        "online_id.core.poles, online_id.core.kalman, online_id.bench.simulate; "
        "bad = [m for m in ('can', 'cantools', 'matplotlib', 'online_id.config', 'online_id.io') if m in sys.modules]; "
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
