#version 330 core
uniform vec3 uLinearDepth;     // depth.linear.near, depth.linear.far, 1.0 with output.reversed_z (else 0.0)
uniform vec2 uLinearOffset;    // depth.linear.slope_scaled, depth.linear.slope_clamp
in float vLightDistance;
void main() {
    float d = (vLightDistance - uLinearDepth.x) / (uLinearDepth.y - uLinearDepth.x);
    float dz = max(abs(dFdx(d)), abs(dFdy(d)));               // change of D per texel step
    d = clamp(d + min(uLinearOffset.x * dz, uLinearOffset.y), 0.0, 1.0);
    gl_FragDepth = uLinearDepth.z > 0.5 ? 1.0 - d : d;
}
