"""The scene store: massive polygon scenes as objects with LOD levels, out of core (zarr v3).

:class:`SceneStore` reads (skeleton, culling groups, ``get_mesh``); :class:`SceneWriter`
writes with bounded memory and resumes; :func:`prepare_scene` ingests mesh files;
:func:`verify_scene` checks a store object by object.
"""

from .mesh import Mesh
from .store import FORMAT, FORMAT_VERSION, GroupTree, SceneStore, Skeleton, is_scene_store
from .writer import SceneWriter

__all__ = ["Mesh", "SceneStore", "Skeleton", "GroupTree", "SceneWriter", "FORMAT", "FORMAT_VERSION", "is_scene_store"]
