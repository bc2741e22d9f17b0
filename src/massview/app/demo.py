"""``massview demo``: the main job on built-in data, end to end.

1. a synthetic 4097² terrain store (heights exaggerated 2.5×) is generated once and cached (``--cache-dir``, default
   ``~/.cache/massview``), about 10 s;
2. the ``flyover`` path is rendered at 1280×720 on local ranks in ``sort-last:kpatch`` with
   binary-swap compositing (loading ``complete``, so every frame has its full detail);
3. ``frames/``, ``demo.mp4`` (H.264 through imageio-ffmpeg's bundled ffmpeg), ``stats.jsonl``,
   ``summary.json`` and ``report.png`` are written to ``--out``, and a short summary printed.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..core.errors import OutputError

__all__ = ["run_demo", "write_video"]


def write_video(frames_dir: Path, out: Path, fps: int = 30) -> Path:
    """H.264 (yuv420p) of the frames at their own size, pixel for pixel; an odd width or height
    gets one more column or row, a copy of the last (yuv420p needs even sizes). (It was
    rescaled to a multiple of 8, with ffmpeg's warning: 641×361 became 648×368, stretched.)"""
    import imageio_ffmpeg
    import numpy as np
    from PIL import Image

    files = sorted(frames_dir.glob("*.png"))
    if not files:
        raise FileNotFoundError(f"no frames in {frames_dir}")
    with Image.open(files[0]) as im:
        width, height = im.size
    size = (width + width % 2, height + height % 2)
    w = imageio_ffmpeg.write_frames(str(out), size, fps=fps, codec="libx264", pix_fmt_out="yuv420p", quality=7,
                                    macro_block_size=1, ffmpeg_log_level="error")
    w.send(None)
    for f in files:
        with Image.open(f) as im:
            rgb = np.asarray(im.convert("RGB"))
        if rgb.shape[:2] != (size[1], size[0]):
            rgb = np.pad(rgb, ((0, size[1] - rgb.shape[0]), (0, size[0] - rgb.shape[1]), (0, 0)), mode="edge")
        w.send(np.ascontiguousarray(rgb))
    w.close()
    if not _whole_mp4(out):  # ffmpeg's failure (a full disk at the trailer) does not reach us otherwise (walk9 M2)
        out.unlink(missing_ok=True)
        raise OutputError(f"could not write the video {out}: ffmpeg did not finish it (its message is above; a full disk?); "
                          f"the frames are in {frames_dir}")
    return out


def _whole_mp4(path: Path) -> bool:
    """Whether ``path`` is an MP4 whose top-level boxes run exactly to its end and include the
    index (``moov``, written last): a file cut short or never finished has not."""
    try:
        size, pos, kinds = path.stat().st_size, 0, set()
        with open(path, "rb") as f:
            while pos < size:
                f.seek(pos)
                head = f.read(16)
                if len(head) < 8:
                    return False
                n = int.from_bytes(head[:4], "big")
                if n == 1:
                    n = int.from_bytes(head[8:16], "big")
                elif n == 0:
                    n = size - pos
                if n < 8:
                    return False
                kinds.add(head[4:8])
                pos += n
        return pos == size and b"moov" in kinds
    except OSError:
        return False


def run_demo(args) -> int:
    from rich.console import Console

    from .. import api
    from .outputs import check_output_dir
    from .report import load_run, print_summary, write_report
    from .terrain_cmds import progress_bar

    console = Console(stderr=True)
    out = check_output_dir(Path(args.out), "--out")  # before minutes of work, not after
    cache = Path(os.path.expanduser(args.cache_dir))
    store = cache / f"demo_terrain_{args.terrain_size}.zarr"
    if not (store / "zarr.json").exists() or not _complete(store):
        console.print(f"[bold]1/3[/] generating the demo terrain ({args.terrain_size}² samples) into {store} (once) ...")
        from ..data.terrain import prepare_terrain
        from ..data.terrain.synthetic import SyntheticSource

        check_output_dir(cache, "--cache-dir")
        with progress_bar() as prog:
            prepare_terrain(SyntheticSource(args.terrain_size, 1), store, vertical_scale=2.5, overwrite=True, progress=prog)
    else:
        console.print(f"[bold]1/3[/] using the cached demo terrain {store}")
    console.print(f"[bold]2/3[/] rendering {args.frames} frames of the flyover at 1280x720 on {args.ranks} ranks (sort-last:kpatch, binary-swap) ...")
    try:
        api.render(store, "flyover", ranks=args.ranks, out=out, images=False, frames=args.frames, size=(1280, 720),
                   decomposition="sort-last:kpatch", compositor="binary-swap", loading="complete")
    except api.RankJobError as e:  # the failing rank printed its message already
        return e.returncode
    console.print("[bold]3/3[/] writing demo.mp4 and report.png ...")
    video = write_video(out / "frames", out / "demo.mp4")
    summary, records = load_run(out)
    report = write_report(out, records, summary)
    print_summary(summary)
    print(f"fps {summary['fps']}, {summary['triangles_per_frame'] / 1e3:.0f} k triangles per frame, "
          f"imbalance {summary['imbalance']}, {summary['bytes_per_frame'] / 1e6:.2f} MB per frame on the wire")
    print(f"wrote {out}/frames/ ({summary['frames']} PNG), {video}, {out}/stats.jsonl, {out}/summary.json, {report}")
    return 0


def _complete(store: Path) -> bool:
    try:
        attrs = json.loads((store / "zarr.json").read_text())["attributes"]
        from ..data.terrain import FORMAT_VERSION

        return bool(attrs.get("complete")) and attrs.get("format_version") == FORMAT_VERSION  # an older cache is rebuilt
    except (OSError, KeyError, ValueError):
        return False
