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


def test_sink_thread_runs_the_sink_off_the_caller_in_order_and_reraises_its_error():
    import numpy as np

    from massview.core.camera import Viewport
    from massview.core.image import blank_image
    from massview.systems.frameloop import SinkThread

    seen, threads = [], set()

    def slow_sink(frame, image):
        time.sleep(0.02)
        threads.add(threading.current_thread().name)
        seen.append((frame, int(image.color[0, 0, 0])))

    images = []
    for f in range(6):
        im = blank_image(Viewport(0, 0, 4, 3))
        im.color[...] = f
        images.append(im)
    with SinkThread(slow_sink, depth=2) as sink:
        for f, im in enumerate(images):
            sink(f, im)
    assert seen == [(f, f) for f in range(6)]  # every frame, in order, all written by close
    assert threads == {"massview-sink"} and threading.current_thread().name not in threads

    def failing(frame, image):
        if frame == 1:
            raise OSError(f"disk full at frame {frame}")
        seen.append(frame)

    seen.clear()
    sink = SinkThread(failing, depth=1)
    with pytest.raises(OSError, match="disk full at frame 1"):
        for f, im in enumerate(images):
            sink(f, im)
        sink.close()
    assert seen == [0]  # frames after the failing one are dropped
    sink.close()  # the error was raised once
    with pytest.raises(Exception, match="after close"):
        sink(9, images[0])
    with pytest.raises(Exception, match="depth"):
        SinkThread(failing, depth=0)
    assert np.all(images[5].color == 5)  # the caller's images are left alone
