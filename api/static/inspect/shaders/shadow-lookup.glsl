#define MAX_CASCADES 6           // up to 4 cascades, or a point light's 6 cube faces
layout(std140) uniform ShadowMaps {  // entry k: map k of the light, in the solution's order
    mat4 uTexMatrix[MAX_CASCADES];   // texture_matrix
    mat4 uLightView[MAX_CASCADES];   // view_matrix (read for depth.mode "linear")
    vec4 uDepth[MAX_CASCADES];       // depth[mode]: constant, slope, normal_offset; w: 1 linear, 0 hardware
    vec4 uLinear[MAX_CASCADES];      // depth.linear.near, depth.linear.far; resolution (texels): width, height
    vec4 uCascade[MAX_CASCADES];     // split near, far; blend_band start, end (last map: split far twice)
    vec4 uToLight;                   // xyz: unit vector towards the light (-direction), w 0; spot, point: position, w 1
    vec4 uParams;                    // x: number of maps; y: 1 with output.reversed_z, else 0; z: 1 for cube faces
};
uniform sampler2DArray uShadowMap;   // layer k: map k's stored depth at its lower left; point sampling, no comparison

float shadowMapVisibility(int k, vec3 worldPos, vec3 N, out bool inside) {
    inside = false;
    vec3 L = uToLight.w > 0.5 ? normalize(uToLight.xyz - worldPos) : uToLight.xyz;
    N = normalize(N);
    if (dot(N, L) < 0.0) N = -N;                              // the side facing the light
    vec3 X = worldPos + uDepth[k].z * N;                      // normal offset
    if (uToLight.w > 0.5) L = normalize(uToLight.xyz - X);    // a spot or point light: from X
    float cosPsi = clamp(dot(N, L), 0.0, 1.0);
    float tanPsi = min(sqrt(1.0 - cosPsi * cosPsi) / max(cosPsi, 1e-6), 10.0);
    vec4 p = uTexMatrix[k] * vec4(X, 1.0);
    if (p.w <= 0.0) return 1.0;                               // behind a warped map's centre
    vec3 stz = p.xyz / p.w;                                   // s, t, hardware depth
    float d = stz.z;
    if (uDepth[k].w > 0.5) {                                  // linear depth, as the light pass writes it
        d = (-(uLightView[k] * vec4(X, 1.0)).z - uLinear[k].x) / (uLinear[k].y - uLinear[k].x);
        if (uParams.y > 0.5) d = 1.0 - d;
    }
    vec3 q = vec3(stz.xy, d);
    if (any(lessThan(q, vec3(0.0))) || any(greaterThan(q, vec3(1.0)))) return 1.0;   // outside: lit
    inside = true;
    ivec2 size = ivec2(uLinear[k].zw);                        // map k's own resolution
    ivec2 texel = min(ivec2(stz.xy * vec2(size)), size - 1);  // the nearest texel
    float stored = texelFetch(uShadowMap, ivec3(texel, k), 0).r;
    float bias = uDepth[k].x + uDepth[k].y * tanPsi;
    bool shadowed = uParams.y > 0.5 ? d + bias < stored : d - bias > stored;   // reversed-Z flips the test
    return shadowed ? 0.0 : 1.0;
}

float shadowVisibility(vec3 worldPos, vec3 N, float viewDepth) {
    int last = int(uParams.x) - 1;
    int k = 0;
    while (k < last && viewDepth > uCascade[k].y) k++;        // the map whose split holds viewDepth
    bool inside;
    float v = shadowMapVisibility(k, worldPos, N, inside);
    if (k < last && viewDepth > uCascade[k].z) {              // in k's blend band: towards map k + 1 ...
        float next = shadowMapVisibility(k + 1, worldPos, N, inside);
        float w = (viewDepth - uCascade[k].z) / (uCascade[k].w - uCascade[k].z);
        if (inside) v = mix(v, next, w);                      // ... where map k + 1 holds the point
    }
    return v;
}
