// Per-pixel terrain shading (included by terrain.frag.glsl, forward, and terrain_shade.frag.glsl,
// deferred): the colour of the terrain at finest-sample coordinates `grid`, shading pyramid
// level `lod` (terrain_lod.glsl, included with it: u_top) and world height `z` (world x, y are
// the grid's: x = col·dx, y = −row·dy). MODE (a compile-time constant, one program per colour
// mode) picks the base colour: 0 the ramp, 1 the orthophoto, 2 grey; only its fetches run.
uniform vec4 u_tint;
uniform sampler2DArray u_shade;
uniform sampler2DArray u_ortho;
uniform isampler2D u_pages;   // slot of block (level, i, j) at (j, row0[level] + i), -1 if absent
uniform sampler2D u_ramp;     // 256 × 1 colour ramp over the height range
const int u_M = BLOCK_M;       // samples per block side
uniform int u_pagerow[16];
uniform vec2 u_spacing;       // dx, dy: metres per finest sample
uniform float u_slope_scale;  // vertical scale × exaggeration
uniform vec3 u_sun;           // unit vector towards the sun
uniform vec2 u_light;         // sky (ambient) and sun weights
uniform vec3 u_eye;
uniform float u_haze;         // extinction per world unit
uniform float u_haze_from;    // haze starts this far from the eye (0 unless the eye stands far back)
vec3 sky_color(vec3 dir);

// shading maps (slope x, slope y, height fraction) and orthophoto colour at level lv or the
// first resident level above it
void fetch(int lv, vec2 g, out vec3 shade, out vec3 rgb) {
    for (; lv <= u_top; ++lv) {
        int span = (u_M - 1) << lv;
        int nb = 1 << (u_top - lv);
        ivec2 b = clamp(ivec2(floor(g / float(span))), ivec2(0), ivec2(nb - 1));
        int slot = texelFetch(u_pages, ivec2(b.x, u_pagerow[lv] + b.y), 0).r;
        if (slot >= 0) {
            vec3 uvw = vec3(((g - vec2(b * span)) / float(1 << lv) + 0.5) / float(u_M), float(slot));
            shade = texture(u_shade, uvw).rgb;
#if MODE == 1
            rgb = texture(u_ortho, uvw).rgb;
#else
            rgb = vec3(0.0);
#endif
            return;
        }
    }
    shade = vec3(0.0, 0.0, 0.5);
    rgb = vec3(0.5);
}

vec4 terrain_color(vec2 grid, float lod, float z) {
    int l0 = int(floor(lod));
    vec3 s, rgb;
    fetch(l0, grid, s, rgb);
    float fr = lod - float(l0);
    if (fr > 0.0 && l0 < u_top) {
        vec3 s1, rgb1;
        fetch(l0 + 1, grid, s1, rgb1);
        s = mix(s, s1, fr);
        rgb = mix(rgb, rgb1, fr);
    }
    vec3 n = normalize(vec3(-u_slope_scale * s.x, -u_slope_scale * s.y, 1.0));
#if MODE == 0
    vec3 base = texture(u_ramp, vec2(clamp(s.z, 0.0, 1.0) * (255.0 / 256.0) + 0.5 / 256.0, 0.5)).rgb;
#elif MODE == 1
    vec3 base = rgb;
#else
    vec3 base = vec3(0.82);
#endif
    float light = u_light.x * (0.5 + 0.5 * n.z) + u_light.y * max(dot(n, u_sun), 0.0);
    vec3 c = base * light;
    vec3 view = vec3(grid.x * u_spacing.x, -grid.y * u_spacing.y, z) - u_eye;
    float fog = 1.0 - exp(-u_haze * max(length(view) - u_haze_from, 0.0));
    c = mix(c, sky_color(view), fog);
    return vec4(mix(c, u_tint.rgb, u_tint.a), 1.0);
}
