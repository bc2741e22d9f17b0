#version 330
// Deferred terrain shading, pass 1 (geometry): what terrain.frag.glsl's shading reads, written
// per pixel instead of shaded, in one RGBA32F target: finest-sample coordinates, world height
// and the shading pyramid level from the screen derivatives of the coordinates (taken here, on
// the fragment's own triangle, exactly as the forward shader takes them). The target is
// cleared to w = -1 before the pass: pass 2 shades only pixels written here. With sub-pixel
// triangles every covered pixel costs a whole 4×4 shading block on llvmpipe; the heavy shading
// then runs once per pixel in pass 2 (terrain_shade.frag.glsl).
uniform vec2 u_extent;        // last valid col, last valid row (finest samples)
in vec2 v_grid;
in float v_z;
out vec4 g_out;               // grid.xy, world z, pyramid level (>= 0)

float terrain_lod(vec2 gx, vec2 gy);

void main() {
#if PADDED
    if (v_grid.x > u_extent.x || v_grid.y > u_extent.y) discard;
#endif
    g_out = vec4(v_grid, v_z, terrain_lod(dFdx(v_grid), dFdy(v_grid)));
}
