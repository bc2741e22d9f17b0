#version 330
// Deferred terrain shading, pass 2: one full-screen triangle; every pixel that pass 1 wrote
// in this draw (level >= 0; the G-buffer is cleared to -1 before each draw) gets
// terrain_color() of exactly the inputs the forward shader would have had, so the image is the
// forward one bit for bit.
uniform sampler2D u_g0;       // grid.xy, world z, level   (float32, terrain_gbuffer.frag.glsl)
out vec4 f_color;

vec4 terrain_color(vec2 grid, float lod, float z);

void main() {
    vec4 g = texelFetch(u_g0, ivec2(gl_FragCoord.xy), 0);
    if (g.w < 0.0) discard;
    f_color = terrain_color(g.xy, g.w, g.z);
}
