"""Issue 33's figure: the real CT head (../shared/data/ct-head-128x128x53.nii.gz) submitted,
watched (at least 3 progress events) and fetched from Python against a real server, with the
job's default parameters. Skips when the shared data is absent. Writes its timings to
$DECIMA_PYCLIENT_FIGURES (JSON) when set."""
import json
import os
import time

import pytest

import decima_client

from conftest import TOKEN

CT_HEAD = "ct-head-128x128x53.nii.gz"


def test_the_ct_head_is_submitted_watched_and_fetched(server, tmp_path):
    path = os.path.join(os.environ.get("DECIMA_SHARED_DATA", ""), CT_HEAD)
    if not os.path.isfile(path):
        pytest.skip(f"{CT_HEAD} is not in DECIMA_SHARED_DATA ({path})")
    client = decima_client.Client(server.address, token=TOKEN)
    t0 = time.monotonic()
    job = client.submit(path)
    t_submit = time.monotonic() - t0
    progress, stages = 0, []
    for ev in job.watch():
        if ev.WhichOneof("kind") == "progress":
            progress += 1
            if not stages or stages[-1] != ev.progress.stage:
                stages.append(ev.progress.stage)
    t_job = time.monotonic() - t0 - t_submit
    job.wait(timeout=30)
    t1 = time.monotonic()
    paths = job.fetch(tmp_path / "ct")
    t_fetch = time.monotonic() - t1
    assert progress >= 3, progress
    assert {"mesh.vtu", "labels.nii.gz", "metrics.json"} <= {os.path.basename(p) for p in paths}
    assert job.metrics["input"]["dims"] == [128, 128, 53]
    assert job.metrics["simplification"]["achieved_reduction"] > 0
    figures = {
        "submit_seconds": round(t_submit, 2), "watch_seconds": round(t_job, 2),
        "fetch_seconds": round(t_fetch, 2), "progress_events": progress, "stages": stages,
        "artifacts": len(paths), "artifact_bytes": sum(os.path.getsize(p) for p in paths),
    }
    out = os.environ.get("DECIMA_PYCLIENT_FIGURES")
    if out:
        with open(out, "w", encoding="utf-8") as f:
            json.dump(figures, f)
    client.close()
