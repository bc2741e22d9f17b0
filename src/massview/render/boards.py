"""Creating Reliefboards on a backend's GPU and drawing them on the visualization rank (§5, §6.1).

:class:`BoardBuilder` renders one object orthographically, facing the requested direction, at
the requested resolution, in **four passes** — distance, stencil, colour, normal — each with its
own small fragment shader into its own single-attachment target (no multiple render targets,
as the paper does for old backend GPUs), reads the maps back and builds the
:class:`~massview.lod.reliefboard.Reliefboard` grid mesh from them.

:class:`BoardRenderer` holds the boards that arrived, one GPU buffer set per object, and draws
them with the **same shaders and light as the original meshes** (``mesh.vert``/``mesh.frag``:
two-sided Lambert on the board's stored unlit colour and normal), at the object's position in
the orientation each was created in — not turned towards the viewer.
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..lod.reliefboard import BoardFrame, Reliefboard, board_frame
from .context import load_shader
from .meshes import _LIGHT, translated

__all__ = ["BoardBuilder", "BoardRenderer", "MAP_PASSES"]

# pass name -> (fragment shader, components, dtype) of the target texture
MAP_PASSES = {
    "distance": ("board_distance.frag.glsl", 1, "f4"),
    "stencil": ("board_stencil.frag.glsl", 1, "f1"),
    "color": ("board_color.frag.glsl", 4, "f1"),
    "normal": ("board_normal.frag.glsl", 4, "f4"),
}


def _vao(ctx, prog, buffers, ibo):
    """A VAO binding only the attributes the linked program kept."""
    names = ("in_pos", "in_normal", "in_color")
    fmts = ("3f", "3f", "4f1")
    content = [(buf, fmt, name) for buf, fmt, name in zip(buffers, fmts, names) if name in prog]
    return ctx.vertex_array(prog, content, index_buffer=ibo, index_element_size=4)


class BoardBuilder:
    """Four-pass Reliefboard creation for one object mesh at a time (a backend's job).

    ``BoardBuilder.process_passes`` counts the capture passes run by every builder in this
    process (the visualization rank reports it: it must stay 0 there)."""

    process_passes = 0

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        vert = load_shader("board_capture.vert.glsl")
        self.progs = {k: ctx.program(vertex_shader=vert, fragment_shader=load_shader(f)) for k, (f, _, _) in MAP_PASSES.items()}
        self.passes_run = 0

    def capture(self, frame: BoardFrame, positions, normals, colors, indices, origin=None) -> dict[str, np.ndarray]:
        """The four (S, S[, C]) maps of a mesh (rows from the bottom), one render pass each;
        ``positions`` relative to ``origin`` (world, float64; None: the world origin)."""
        ctx, s = self.ctx, frame.size
        bufs = [ctx.buffer(np.ascontiguousarray(positions, "f4")), ctx.buffer(np.ascontiguousarray(normals, "f4")),
                ctx.buffer(np.ascontiguousarray(colors, "u1"))]
        ibo = ctx.buffer(np.ascontiguousarray(indices, "u4"))
        depth = ctx.depth_renderbuffer((s, s))
        view = np.ascontiguousarray(translated(frame.view_matrix(), origin).T, "f4").tobytes()
        proj = np.ascontiguousarray(frame.projection_matrix().T, "f4").tobytes()
        maps = {}
        try:
            for name, (_, comps, dtype) in MAP_PASSES.items():
                maps[name] = self._pass(name, comps, dtype, s, depth, bufs, ibo, view, proj, frame.radius)
        finally:
            for obj in (*bufs, ibo, depth):
                obj.release()
        return maps

    def _pass(self, name, comps, dtype, s, depth, bufs, ibo, view, proj, radius):
        ctx, prog = self.ctx, self.progs[name]
        tex = ctx.texture((s, s), comps, dtype=dtype)
        fbo = ctx.framebuffer(color_attachments=[tex], depth_attachment=depth)
        vao = _vao(ctx, prog, bufs, ibo)
        try:
            fbo.use()
            ctx.scissor = None
            fbo.viewport = (0, 0, s, s)
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.depth_func = "<"
            ctx.disable(moderngl.CULL_FACE)
            prog["u_view"].write(view)
            prog["u_proj"].write(proj)
            if "u_radius" in prog:
                prog["u_radius"].value = float(radius)
            vao.render(moderngl.TRIANGLES)
            raw = fbo.read(components=comps, dtype=dtype)
            self.passes_run += 1
            BoardBuilder.process_passes += 1
        finally:
            vao.release()
            fbo.release()
            tex.release()
        arr = np.frombuffer(raw, np.float32 if dtype == "f4" else np.uint8)
        return arr.reshape(s, s, comps) if comps > 1 else arr.reshape(s, s)

    def build(self, object_id: int, positions, normals, colors, indices, direction, size: int,
              box_lo=None, box_hi=None, origin=None) -> Reliefboard:
        """A Reliefboard of one object mesh (float32 positions (V, 3) in world axes relative to
        ``origin`` (world, float64; None: the world origin), world normals (V, 3), uint8 colours
        (V, 4), uint32 indices (3T,)) for ``direction`` (observer → object centre) at ``size`` ×
        ``size`` pixels. The frame is the mesh's world box unless given."""
        pos = np.asarray(positions, np.float32)
        o = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
        lo = pos.min(axis=0) + o if box_lo is None else box_lo
        hi = pos.max(axis=0) + o if box_hi is None else box_hi
        frame = board_frame(lo, hi, direction, size)
        maps = self.capture(frame, pos, normals, colors, indices, o)
        cover = maps["stencil"] > 127
        return Reliefboard(int(object_id), frame, cover, maps["distance"][cover].astype(np.float32),
                           maps["color"][cover][:, :3].copy(), maps["normal"][cover][:, :3].copy())

    def release(self) -> None:
        for p in self.progs.values():
            p.release()


class BoardRenderer:
    """Resident boards of the visualization rank, drawn lit like the original meshes."""

    def __init__(self, ctx: moderngl.Context, light=None):
        self.ctx = ctx
        self.prog = ctx.program(vertex_shader=load_shader("mesh.vert.glsl"), fragment_shader=load_shader("mesh.frag.glsl"))
        self.set_light(_LIGHT if light is None else light)
        self._boards: dict[int, tuple] = {}

    def set_light(self, light) -> None:
        """Directional light (world space, normalized here), the same uniform the meshes use."""
        v = np.asarray(light, np.float64)
        self.prog["u_light"].value = tuple((v / np.linalg.norm(v)).astype("f4"))

    def __contains__(self, object_id: int) -> bool:
        return int(object_id) in self._boards

    @property
    def gpu_bytes(self) -> int:
        return sum(b.size for entry in self._boards.values() for b in entry[1])

    def triangles(self, object_id: int) -> int:
        """Triangles of the object's resident board (0 if none)."""
        entry = self._boards.get(int(object_id))
        return 0 if entry is None else entry[2]

    def put(self, board: Reliefboard, flat: bool = False) -> None:
        """Upload ``board`` (replacing the object's previous board)."""
        self.remove(board.object_id)
        pos, nrm, rgba, idx = board.mesh(flat=flat)
        if len(idx) == 0:
            return
        bufs = [self.ctx.buffer(pos), self.ctx.buffer(nrm), self.ctx.buffer(rgba)]
        ibo = self.ctx.buffer(idx)
        self._boards[int(board.object_id)] = (_vao(self.ctx, self.prog, bufs, ibo), (*bufs, ibo), len(idx) // 3,
                                              np.asarray(board.frame.center, np.float64))

    def remove(self, object_id: int) -> None:
        entry = self._boards.pop(int(object_id), None)
        if entry is not None:
            entry[0].release()
            for b in entry[1]:
                b.release()

    def draw(self, object_ids, mvp: np.ndarray, tint=(0.0, 0.0, 0.0, 0.0)) -> int:
        """Draw the boards of ``object_ids`` (those resident) with the float64 4x4 ``mvp``
        (times each board's centre translation, in float64: board vertices are stored relative
        to it); returns the triangles submitted."""
        self.prog["u_tint"].value = tuple(tint)
        tris = 0
        for oid in object_ids:
            entry = self._boards.get(int(oid))
            if entry is not None:
                self.prog["u_mvp"].write(np.ascontiguousarray(translated(mvp, entry[3]).T, dtype="f4").tobytes())
                entry[0].render(moderngl.TRIANGLES)
                tris += entry[2]
        return tris

    def release(self) -> None:
        for oid in list(self._boards):
            self.remove(oid)
        self.prog.release()
