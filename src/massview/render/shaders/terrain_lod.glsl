// The shading pyramid level of a pixel from the screen derivatives of its finest-sample
// coordinates (gx = dFdx(grid), gy = dFdy(grid)): log2 of the footprint, in [0, L]. Shared by
// the forward shader and the deferred geometry pass (terrain_shading.glsl reads u_top too).
uniform int u_top;            // top pyramid level L
float terrain_lod(vec2 gx, vec2 gy) {
    return clamp(log2(max(max(length(gx), length(gy)), 1e-6)), 0.0, float(u_top));
}
