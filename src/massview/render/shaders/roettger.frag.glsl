#version 330
// T2 terrain with T1's shading options (massview.render.colormaps.Shading): the colour ramp
// (--colormap) over the height range, the sun (--sun) and sky light on the facet normal (from
// screen-space derivatives: the fans carry no normals), aerial perspective towards the sky
// colour (--haze, as terrain_shading.glsl). Padding samples beyond the input extent are
// discarded; u_tint_on mixes in a colour per computation rank (the rank that produced the fan).
// With u_drape_on the base colour is the store's orthophoto (one level of it, draped whole,
// mipmapped: massview.data.terrain.drape) instead of the ramp, lit as T1 lights it.
uniform vec3 u_sun;      // unit vector towards the sun
uniform vec2 u_light;    // sky (ambient) and sun weights
uniform vec2 u_extent;   // last valid col, last valid row
uniform vec2 u_zrange;   // height range for the colour ramp
uniform sampler2D u_ramp;  // 256 × 1 colour ramp over the height range
uniform vec3 u_eye;
uniform float u_haze;       // extinction per world unit
uniform float u_haze_from;  // haze starts this far from the eye
uniform int u_tint_on;
uniform int u_drape_on;
uniform sampler2D u_drape;  // the orthophoto: texel (c, r) = finest sample (c, r) · 2^level
uniform vec2 u_drape_map;   // 1 / 2^level, the image's side in texels
uniform vec3 u_tints[8];
in vec3 v_world;
in float v_h;
in vec2 v_grid;
flat in int v_rank;
out vec4 f_color;
vec3 sky_color(vec3 dir);
void main() {
    if (v_grid.x > u_extent.x || v_grid.y > u_extent.y) discard;
    vec3 n = normalize(cross(dFdx(v_world), dFdy(v_world)));
    if (n.z < 0.0) n = -n;
    float u = clamp((v_h - u_zrange.x) / max(u_zrange.y - u_zrange.x, 1e-6), 0.0, 1.0);
    vec3 base = u_drape_on != 0 ? texture(u_drape, (v_grid * u_drape_map.x + 0.5) / u_drape_map.y).rgb
                                : texture(u_ramp, vec2(u * (255.0 / 256.0) + 0.5 / 256.0, 0.5)).rgb;
    vec3 c = base * (u_light.x * (0.5 + 0.5 * n.z) + u_light.y * max(dot(n, u_sun), 0.0));
    vec3 view = v_world - u_eye;
    c = mix(c, sky_color(view), 1.0 - exp(-u_haze * max(length(view) - u_haze_from, 0.0)));
    if (u_tint_on != 0) c = mix(c, u_tints[v_rank % 8], 0.55);
    f_color = vec4(c, 1.0);
}
