"""A recorder stalled long enough for DDS to drop its readers (the issue: `kill -STOP` for 45
s, split layout, 94 % of the run lost without a word and `run` hung) ends with a bag that
says what it lacks and why, and the run ends by itself. Scaled down: every process of the
graph runs with a Fast DDS participant lease of 2 s (announced every 0.5 s) instead of the
default 20 s, and the recorder is stopped for 6 s: the other participants drop it (lease)
and, the lockstep graph not waiting for it, the writers' history of 10 000 samples runs over
it too (the stall lasts until the plant is 12 000 frames further) -- the same mechanisms as
45 s at the default lease. After `kill -CONT` the recorder is matched again and gets the
writers' history: the frames jump. The recorder logs the jump (`seq jumps from a to b: n
messages never reached the recorder ...`), its final line and the bag's metadata
(`fluxdrive_missing`) say how many; the launcher's end-of-run check names every topic that
is short against its publisher's count, in its log and the same metadata.  On a loaded
machine the match may come only after the drive has ended: then the recorder's stop names
what the gone publishers sent and it lacks."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

from test_process_faults import Run, graph_dict, short_lease  # noqa: E402

STALL_S = 6.0  # 3 leases: the recorder's participant is dropped for certain


def test_recorder_stalled_past_its_lease_says_what_is_missing_and_why(tmp_path):
    from fluxdrive.core import yamlio

    bag = tmp_path / "bag"
    g = graph_dict(
        bag, duration_s=3.0, processes={"recorder": "recorder"}, defaults=short_lease(tmp_path, 2)
    )
    g["nodes"][0]["required"] = True
    run = Run(g, domain(33), tmp_path).start()
    run.wait_frames(2000, timeout=400)  # kernels may compile first
    pid = run.pid("recorder")
    os.kill(pid, signal.SIGSTOP)
    k_stop = run.frames()
    time.sleep(STALL_S)  # the stall is the input: a stated length of time ...
    run.wait_frames(k_stop + 12000, timeout=400)  # ... and past the writers' history
    k_cont = run.frames()
    os.kill(pid, signal.SIGCONT)
    code = run.join(timeout=240)  # the run ends by itself (Run: launcher timeout 150 s)
    text = run.text()
    print("\n".join(ln for ln in run.lines if "[launch]" in ln or "[recorder]" in ln))
    print(f"recorder stopped from frame {k_stop} to {k_cont}")
    assert code == 0, text
    assert "done: 30000 frames" in text  # the drive ran to its end
    custom = yamlio.load_file(bag / "metadata.yaml")["rosbag2_bagfile_information"]
    note = json.loads(custom["custom_data"]["fluxdrive_missing"])
    # the launcher's count check against the publishers: the frames missing, named
    short = note["topics"]["/drive/frame"]
    missing = short["published"] - short["recorded"]
    assert short["published"] == 30000 and missing > 0
    assert f"messages published on /drive/frame ({missing} missing)" in text
    # and the recorder's own word on why.  Two ways it goes, by how long the other
    # participants take to match the woken recorder again: matched while the drive still
    # runs, it gets the writers' history and the frames jump (published, never received);
    # not matched before the drive's end, its stop names what the gone publishers sent
    if "/drive/frame: seq jumps from" in text:
        assert "never reached the recorder" in text
        lost = note["lost_in_transit"]["/drive/frame"]
        final = next(ln for ln in run.lines if "finalised:" in ln)
        assert lost > 0 and f"/drive/frame {lost}" in final.split("never received (seq gaps): ")[1]
        assert any("seq gaps" in w for w in note["why"])
        assert lost == missing
    else:
        stop = next(ln for ln in run.lines if "stop: the bag lacks messages" in ln)
        assert f"/drive/frame {short['recorded']} of 30000 ({missing} missing)" in stop
        assert "their publishers are gone" in stop
