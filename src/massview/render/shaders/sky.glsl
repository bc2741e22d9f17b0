// Sky gradient: the colour aerial perspective fades to (the background itself is painted by
// massview.render.colormaps.paint_sky with the same formula).
uniform vec3 u_sky_horizon;
uniform vec3 u_sky_zenith;
vec3 sky_color(vec3 dir) {
    float e = dir.z / max(length(dir), 1e-20);
    return mix(u_sky_horizon, u_sky_zenith, smoothstep(-0.05, 0.6, e));  // as colormaps.paint_sky
}
