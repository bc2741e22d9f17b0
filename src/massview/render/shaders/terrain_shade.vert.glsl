#version 330
// Deferred terrain shading, pass 2: one triangle covering the viewport, on the far plane
// (window depth 1.0, the depth the target is cleared to). Drawn with the depth test GREATER
// and no depth writes against the target's depth, which pass 1 wrote, so a pixel that no
// terrain covers (sky: depth still 1.0) fails the test before the shading fragment shader runs
// (llvmpipe tests depth early for a shader without depth writes, and skips a 4×4 stamp whose
// pixels all fail). Every pixel pass 1 wrote has depth < 1.0 and passes.
void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 1.0, 1.0);
}
