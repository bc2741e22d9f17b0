#version 330
// Unlit store colours lit at view time: a key light (Lambert), a fill light half as strong
// from the opposite side and a sky/ground hemisphere ambient term by the normal's z, on the
// side of the surface the eye sees (the normal turned towards the eye: meshes are lit on both
// sides, whatever their winding). Before, the key was |n·L|, which lit undersides as brightly
// as tops and gave a box's opposite faces one shade.
// u_tint mixes a rank colour in.
uniform vec3 u_light;
uniform vec4 u_tint;
in vec3 v_normal;
in vec3 v_rel;
in vec4 v_color;
out vec4 f_color;
void main() {
    vec3 n = normalize(v_normal);
    if (dot(n, v_rel) > 0.0) n = -n;
    float key = max(dot(n, u_light), 0.0);
    float fill = max(-dot(n, u_light), 0.0);  // a weaker light opposite the key: the far side keeps its form
    float sky = 0.5 + 0.5 * n.z;
    vec3 c = v_color.rgb * (0.22 + 0.18 * sky + 0.6 * key + 0.3 * fill);
    f_color = vec4(mix(c, u_tint.rgb, u_tint.a), 1.0);
}
