#version 330
// Deferred terrain shading, pass 2: one full-screen triangle; every pixel that pass 1 wrote
// in this draw (serial match) gets terrain_color() of exactly the inputs the forward shader
// would have had, so the image is the forward one bit for bit.
uniform sampler2D u_g0;       // grid.xy, dFdx(grid).xy     (float32, terrain_gbuffer.frag.glsl)
uniform sampler2D u_g1;       // dFdy(grid).xy, world.xy
uniform sampler2D u_g2;       // world.z, serial
uniform float u_serial;
out vec4 f_color;

vec4 terrain_color(vec2 grid, vec2 gx, vec2 gy, vec3 world);

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec2 g2 = texelFetch(u_g2, p, 0).xy;
    if (g2.y != u_serial) discard;
    vec4 g0 = texelFetch(u_g0, p, 0);
    vec4 g1 = texelFetch(u_g1, p, 0);
    f_color = terrain_color(g0.xy, g0.zw, g1.xy, vec3(g1.zw, g2.x));
}
