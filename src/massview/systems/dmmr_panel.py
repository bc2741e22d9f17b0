"""The massive-model system's figures for the live viewer's panel (``massview view --system dmmr``).

:func:`panel_rows` turns one frame's statistics records (the server's, rank 0, and each
client's) into ``{label: text}`` rows, per client in client order ("a/b/c"): objects in the
frustum and sent (server), objects received, occlusion queries issued and objects culled,
objects drawn and triangles, the three cache levels (GPU hits, RAM hits, disk loads; meshes
deferred to background loading with ``--loading async``), bytes (uploaded to the GPU, sent
to the server) and the stage times of the three pipeline modules (§3.3: division on the
server, visibility on GPU 1, rendering on GPU 2). With colour-by-rank each client's
sub-frustum is tinted in its own colour.
"""

from __future__ import annotations

__all__ = ["panel_rows"]


def _per(clients: list[dict], fn) -> str:
    return "/".join(fn(r) for r in clients) or "–"


def _c(key: str):
    return lambda r: f"{int(r['counters'].get(key, 0))}"


def _ms(*keys: str):
    return lambda r: f"{sum(r['times_ms'].get(k, 0.0) for k in keys):.0f}"


def _kilo(get):
    return lambda r: f"{get(r) / 1e3:.0f}k"


def panel_rows(server: dict, clients: list[dict]) -> dict[str, str]:
    """``{label: text}`` for one frame; ``clients`` sorted by client (the records' ``rank``)."""
    sc, st = server.get("counters", {}), server.get("times_ms", {})
    tris = _kilo(lambda r: r.get("triangles", 0))
    up = _kilo(lambda r: r["counters"].get("bytes_uploaded", 0))
    sent = _kilo(lambda r: r.get("bytes_sent", 0))
    levels = lambda r: "/".join(str(int(r["counters"].get(k, 0))) for k in ("gpu_hits", "ram_hits", "disk_loads"))  # noqa: E731
    return {
        "M1 objects in frustum / sent": f"{int(sc.get('objects_in_frustum', 0))} / {int(sc.get('objects_sent', 0))}",
        "received per client": _per(clients, _c("objects_received")),
        "occlusion queries / culled": f"{_per(clients, _c('queries_issued'))} / {_per(clients, _c('culled_by_occlusion'))}",
        "drawn objects / triangles": f"{_per(clients, _c('objects_drawn'))} / {_per(clients, tris)}",
        "cache GPU hits/RAM hits/disk loads": " · ".join(levels(r) for r in clients) or "–",
        "deferred (loading) / drawn coarser": f"{_per(clients, _c('deferred'))} / {_per(clients, _c('drawn_coarser'))}",
        "bytes uploaded / sent": f"{_per(clients, up)} / {_per(clients, sent)}",
        "ms divide · visibility · render · assemble": f"{st.get('divide', 0.0):.0f} · {_per(clients, _ms('visibility'))} · "
                                                      f"{_per(clients, _ms('load', 'draw', 'readback', 'encode'))} · {st.get('assemble', 0.0):.0f}",
    }
