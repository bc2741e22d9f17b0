"""The Reliefboards clustering stored beside a scene store's own data (§4; additive layout).

``massview prepare reliefboards SCENE`` adds one sub-group to the scene store's zarr v3 group
and changes nothing else::

    reliefboards/                attrs: version, complete, t_nz, p, r_y, fovy, min_triangles,
                                        d_nz, sl_c (world units), objects, clusters
    reliefboards/labels          int32 (n_objects,)  cluster id of every store object
    reliefboards/status          int8  (n_clusters,) 0 feasible, 1 too large, 2 too few triangles

``complete`` is written last: a clustering interrupted half-way reads as absent. Other programs
read it with plain zarr (``zarr.open_group(SCENE)["reliefboards/labels"][:]``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from ..core.errors import StoreError

__all__ = ["StoredClusters", "write_clusters", "read_clusters", "GROUP"]

GROUP = "reliefboards"
VERSION = 1


@dataclass(frozen=True)
class StoredClusters:
    labels: np.ndarray
    status: np.ndarray
    attrs: dict


def write_clusters(path, labels: np.ndarray, status: np.ndarray, attrs: dict) -> None:
    """(Re)write the ``reliefboards`` sub-group of the zarr group at ``path``."""
    path = Path(path)
    try:
        root = zarr.open_group(str(path), mode="r+")
    except Exception as e:  # zarr raises several kinds for a missing/foreign folder
        raise StoreError(f"{path}: not a scene store this command can add to ({type(e).__name__}: {e}); "
                         "make one with `massview prepare scene` or `massview generate scene`") from None
    if GROUP in root:
        del root[GROUP]
    g = root.create_group(GROUP)
    g.attrs.update({"version": VERSION, "complete": False})
    labels = np.asarray(labels, np.int32)
    status = np.asarray(status, np.int8)
    g.create_array("labels", shape=labels.shape, chunks=(max(1, min(len(labels), 1 << 20)),), dtype="int32")[:] = labels
    g.create_array("status", shape=status.shape, chunks=(max(1, min(len(status), 1 << 20)),), dtype="int8")[:] = status
    g.attrs.update({k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in attrs.items()})
    g.attrs.update({"objects": int(len(labels)), "clusters": int(len(status)), "complete": True})


def read_clusters(path) -> StoredClusters | None:
    """The stored clustering of the scene at ``path``, or None when it has none (or an
    incomplete one)."""
    try:
        root = zarr.open_group(str(path), mode="r")
    except Exception:
        return None
    if GROUP not in root:
        return None
    g = root[GROUP]
    attrs = dict(g.attrs)
    if not attrs.get("complete"):
        return None
    labels, status = np.asarray(g["labels"][:]), np.asarray(g["status"][:])
    if len(labels) != attrs.get("objects") or len(status) != attrs.get("clusters") or labels.max(initial=-1) >= len(status):
        raise StoreError(f"{path}: the reliefboards clustering is inconsistent; run `massview prepare reliefboards` again")
    return StoredClusters(labels, status, attrs)
