"""The terrain renderer's GL programs, specialized at compile time, with their uniforms.

Constants that only change with the store or the colour mode are compiled in (``#define``
lines after ``#version``) instead of read from uniforms, so llvmpipe runs none of the branches
they would select and no per-lane integer division:

* ``BLOCK_M``: samples per block side (vertex index arithmetic, page-table addressing);
* ``PADDED``: 1 when the store has padding samples beyond the input, whose fragments are
  discarded (without padding the geometry pass has no ``discard``);
* ``MODE``: the colour mode (0 ramp, 1 orthophoto, 2 grey); only its texture fetches run.

Three programs: ``forward`` (geometry + shading per fragment), ``gbuffer`` (geometry pass of
the deferred path, :mod:`.terrain_gbuffer`) and ``shade`` (its full-screen pass: one triangle on
the far plane, terrain_shade.vert.glsl, so sky pixels fail its depth test). Changing
the mode recompiles ``forward`` and ``shade`` (once per mode: kept) and replays every uniform
set so far, so callers set uniforms once through :meth:`TerrainPrograms.set`.
"""

from __future__ import annotations

import moderngl

from .context import load_shader

__all__ = ["specialize", "program", "TerrainPrograms"]


def specialize(src: str, **defines) -> str:
    """GLSL ``src`` with ``#define NAME value`` lines after its ``#version`` line."""
    head, _, body = src.partition("\n")
    return "\n".join([head, *(f"#define {k} {v}" for k, v in defines.items()), body])


def program(ctx: moderngl.Context, vert: str, frag: str | None, defines: dict, **kw) -> moderngl.Program:
    """A terrain program from shader files: ``frag`` (None: the vertex stage alone) with the
    shared functions it calls appended (terrain_lod.glsl, terrain_shading.glsl, sky.glsl);
    both stages specialized with ``defines``."""
    vs = specialize(load_shader(vert), **defines)
    if frag is None:
        return ctx.program(vertex_shader=vs, **kw)
    fs = load_shader(frag)
    if "terrain_lod(" in fs or "terrain_color(" in fs:
        fs += load_shader("terrain_lod.glsl")
    if "vec4 terrain_color(" in fs:
        fs += load_shader("terrain_shading.glsl")
    if "sky_color" in fs:
        fs += load_shader("sky.glsl")
    return ctx.program(vertex_shader=vs, fragment_shader=specialize(fs, **defines), **kw)


class TerrainPrograms:
    """``forward``, ``gbuffer`` and ``shade`` programs for blocks of ``M`` samples a side;
    ``padded``: the store has samples beyond the input to discard."""

    def __init__(self, ctx: moderngl.Context, M: int, padded: bool):
        self.ctx = ctx
        self.defines = {"BLOCK_M": int(M), "PADDED": int(bool(padded))}
        self._values: dict[str, object] = {}
        self._by_mode: dict[int, tuple[moderngl.Program, moderngl.Program]] = {}
        self.gbuffer = program(ctx, "terrain.vert.glsl", "terrain_gbuffer.frag.glsl", self.defines)
        self.mode = -1
        self.forward = self.shade = None
        self.set_mode(0)

    def set_mode(self, mode: int) -> bool:
        """Use the programs of colour ``mode``; True when they changed (VAOs must follow)."""
        if mode == self.mode:
            return False
        pair = self._by_mode.get(mode)
        if pair is None:
            d = {**self.defines, "MODE": int(mode)}
            pair = self._by_mode[mode] = (program(self.ctx, "terrain.vert.glsl", "terrain.frag.glsl", d),
                                          program(self.ctx, "terrain_shade.vert.glsl", "terrain_shade.frag.glsl", d))
            for p in pair:
                self._apply(p, self._values)
        self.mode, (self.forward, self.shade) = mode, pair
        return True

    def set(self, name: str, value) -> None:
        """Set a uniform in every program that has it (all modes); ``bytes`` are written raw
        (matrices)."""
        self._values[name] = value
        for p in self.all():
            self._apply(p, {name: value})

    def get(self, name: str):
        return self._values[name]

    def all(self) -> list[moderngl.Program]:
        return [self.gbuffer, *(p for pair in self._by_mode.values() for p in pair)]

    @staticmethod
    def _apply(prog: moderngl.Program, values: dict) -> None:
        for name, value in values.items():
            if name in prog:
                if isinstance(value, bytes):
                    prog[name].write(value)
                else:
                    prog[name].value = value

    def release(self) -> None:
        for p in self.all():
            p.release()
        self._by_mode.clear()
