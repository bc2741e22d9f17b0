"""The three-stage frame pipeline of §3.3 with injected stage delays: period ≈ slowest stage,
latency 3 frames; synchronous reference: period ≈ sum, latency 1. Delays are sleeps, so the
figures do not depend on CPU speed; bounds are loose ratios of the injected delays."""

from __future__ import annotations

import threading
import time

import pytest

from massview.parallel.pipeline import StagePipeline, pipeline_metrics

DELAYS = {"divide": 0.03, "visibility": 0.09, "render": 0.04}
NAMES = list(DELAYS)


def _stages(log):
    def make(name):
        def fn(frame, value):
            time.sleep(DELAYS[name])
            log.append((name, frame, threading.current_thread().name))
            return value + [name]
        return name, fn
    return [make(n) for n in NAMES]


def test_pipelined_period_is_the_slowest_stage_and_latency_three_frames():
    log = []
    p = StagePipeline(_stages(log))
    outs = p.run([[f] for f in range(14)])
    assert outs == [[f, *NAMES] for f in range(14)]  # every frame went through every stage, in order
    m = pipeline_metrics(p.records, NAMES)
    slowest, total = max(DELAYS.values()), sum(DELAYS.values())
    assert m["latency_frames"] == 3
    assert slowest * 0.95 <= m["period_s"] <= slowest + 0.35 * (total - slowest), m
    assert len({t for _, _, t in log}) == 3  # one thread per stage
    # while the renderer works on frame i-2, visibility runs on i-1 and the division on i
    by = {(r.stage, r.frame): r for r in p.records}
    overlaps = sum(1 for f in range(2, 12) if by[("divide", f)].start < by[("render", f - 2)].end
                   and by[("visibility", f - 1)].start < by[("render", f - 2)].end)
    assert overlaps >= 8


def test_synchronous_reference_period_is_the_sum_and_latency_one():
    p = StagePipeline(_stages([]), pipelined=False)
    outs = p.run([[f] for f in range(5)])
    assert outs == [[f, *NAMES] for f in range(5)]
    m = pipeline_metrics(p.records, NAMES, warmup=0)
    assert m["latency_frames"] == 1
    assert m["period_s"] >= 0.95 * sum(DELAYS.values())


def test_a_failing_stage_stops_the_pipeline_and_raises():
    def bad(frame, value):
        if frame == 3:
            raise RuntimeError("stage failed at frame 3")
        return value

    p = StagePipeline([("a", lambda f, v: v), ("b", bad), ("c", lambda f, v: v)])
    with pytest.raises(RuntimeError, match="frame 3"):
        p.run(range(10))
