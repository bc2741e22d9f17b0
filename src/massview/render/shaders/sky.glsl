// Sky gradient shared by the sky pass and the terrain's aerial perspective.
uniform vec3 u_sky_horizon;
uniform vec3 u_sky_zenith;
vec3 sky_color(vec3 dir) {
    float e = dir.z / max(length(dir), 1e-20);
    return mix(u_sky_horizon, u_sky_zenith, smoothstep(-0.05, 0.6, e));  // as colormaps.paint_sky
}
