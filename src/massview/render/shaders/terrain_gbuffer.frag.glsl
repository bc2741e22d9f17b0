#version 330
// Deferred terrain shading, pass 1 (geometry): what terrain.frag.glsl's shading reads, written
// per pixel instead of shaded: finest-sample coordinates and their screen derivatives (taken
// here, on the fragment's own triangle, exactly as the forward shader takes them), the world
// position, and this draw's serial number (pass 2 shades only pixels carrying it). With
// sub-pixel triangles every covered pixel costs a whole shading block on llvmpipe; the heavy
// shading then runs once per pixel in pass 2 (terrain_shade.frag.glsl).
uniform vec2 u_extent;        // last valid col, last valid row (finest samples)
uniform float u_serial;       // this draw's serial, exact in float32 (< 2^24)
in vec2 v_grid;
in vec3 v_world;
layout(location = 0) out vec4 g_grid;   // grid.xy, dFdx(grid).xy
layout(location = 1) out vec4 g_dy;     // dFdy(grid).xy, world.xy
layout(location = 2) out vec2 g_world;  // world.z, serial
void main() {
    if (v_grid.x > u_extent.x || v_grid.y > u_extent.y) discard;
    g_grid = vec4(v_grid, dFdx(v_grid));
    g_dy = vec4(dFdy(v_grid), v_world.xy);
    g_world = vec2(v_world.z, u_serial);
}
