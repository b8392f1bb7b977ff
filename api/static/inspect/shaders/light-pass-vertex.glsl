#version 330 core
uniform mat4 uLightViewProj;   // projection_matrix · view_matrix of this map
uniform mat4 uLightView;       // view_matrix of this map
in vec3 inPosition;            // world-space vertex
out float vLightDistance;      // -z in the light view: distance along the light's axis
void main() {
    vLightDistance = -(uLightView * vec4(inPosition, 1.0)).z;
    gl_Position = uLightViewProj * vec4(inPosition, 1.0);
}
