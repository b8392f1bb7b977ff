float localShadowVisibility(vec3 worldPos, vec3 N, float viewDepth) {
    if (uParams.z < 0.5) return shadowVisibility(worldPos, N, viewDepth);   // a spot: its maps by split
    for (int k = 0; k < int(uParams.x); k++) {                // a point light: the first face holding X'
        bool inside;
        float v = shadowMapVisibility(k, worldPos, N, inside);
        if (inside) return v;
    }
    return 1.0;                                               // outside every listed face: lit
}
