"""The stage log: seconds and the peak memory when each stage ended."""

import json
import subprocess
import sys

import pytest

from dm2_backend.runtime.stage_log import StageLog

_SCRIPT = """
import json, time, numpy as np
from dm2_backend.runtime.stage_log import StageLog
log = StageLog()
with log.stage("small"):
    time.sleep(0.01)
with log.stage("large"):
    block = np.ones(256 * 2**20 // 8)  # 256 MiB, touched
    del block
with log.stage("after"):
    pass
print(json.dumps([log.seconds, log.peak_mb]))
"""


def test_the_stage_that_allocates_is_the_one_whose_peak_rises():
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, check=True).stdout
    seconds, peak = json.loads(out)
    assert list(seconds) == ["small", "large", "after"] and seconds["small"] >= 0.01
    assert peak["large"] - peak["small"] > 200  # the 256 MiB block, in the stage that made it


def test_a_failing_stage_is_not_recorded():
    log = StageLog()
    with pytest.raises(RuntimeError), log.stage("fails"):
        raise RuntimeError("boom")
    assert log.seconds == {} and log.peak_mb == {}
