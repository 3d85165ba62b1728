// The GLSL programs of the map view (GLSL ES 1.00, so they run on WebGL 1 and 2) and the helper
// that compiles them. World positions go to clip space as clip = (p - u_center) * u_scale;
// laser points arrive in their robot's frame and are placed by their pose (SCAN_VS);
// colours are written premultiplied (blend ONE, ONE_MINUS_SRC_ALPHA).

export const POINT_VS = `
attribute vec2 a_pos;
uniform vec2 u_center;
uniform vec2 u_scale;
uniform float u_size;
void main() {
  gl_Position = vec4((a_pos - u_center) * u_scale, 0.0, 1.0);
  gl_PointSize = u_size;
}`;

// Laser points placed by their pose on the GPU: each vertex is a robot-frame point and the index
// of its pose; the poses are a float texture of (x, y, cos theta, sin theta) texels, u_poses_size
// texels wide and high, re-uploaded (a few kilobytes) when the map changes. The points' buffers
// are uploaded once.
export const SCAN_VS = `
attribute vec2 a_local;
attribute float a_pose;
uniform highp sampler2D u_poses;
uniform vec2 u_poses_size;
uniform vec2 u_center;
uniform vec2 u_scale;
uniform float u_size;
void main() {
  float row = floor((a_pose + 0.5) / u_poses_size.x);
  float col = a_pose - row * u_poses_size.x;
  vec4 p = texture2D(u_poses, vec2((col + 0.5) / u_poses_size.x, (row + 0.5) / u_poses_size.y));
  vec2 w = p.xy + vec2(p.z * a_local.x - p.w * a_local.y, p.w * a_local.x + p.z * a_local.y);
  gl_Position = vec4((w - u_center) * u_scale, 0.0, 1.0);
  gl_PointSize = u_size;
}`;

export const POINT_FS = `
precision mediump float;
uniform vec4 u_color;
uniform float u_round;
void main() {
  if (u_round > 0.5 && length(gl_PointCoord - vec2(0.5)) > 0.5) discard;
  gl_FragColor = vec4(u_color.rgb * u_color.a, u_color.a);
}`;

// Every corner of a pose's arrow carries the pose (x, y, theta, in-a-correction flag); corners
// are in arrow lengths, scaled to u_arrow device pixels so arrows keep their size on screen.
export const ARROW_VS = `
attribute vec4 a_pose;
attribute vec2 a_local;
uniform vec2 u_center;
uniform vec2 u_scale;
uniform vec2 u_viewport;
uniform float u_arrow;
uniform vec4 u_plain;
uniform vec4 u_constrained;
varying vec4 v_color;
void main() {
  vec2 c = (a_pose.xy - u_center) * u_scale;
  float ct = cos(a_pose.z);
  float st = sin(a_pose.z);
  vec2 off = vec2(ct * a_local.x - st * a_local.y, st * a_local.x + ct * a_local.y) * u_arrow;
  gl_Position = vec4(c + off * 2.0 / u_viewport, 0.0, 1.0);
  v_color = a_pose.w > 0.5 ? u_constrained : u_plain;
}`;

export const COLOUR_FS = `
precision mediump float;
varying vec4 v_color;
void main() { gl_FragColor = vec4(v_color.rgb * v_color.a, v_color.a); }`;

// Screen-space thick lines: each segment is a quad widened along its on-screen normal, so the
// width is in pixels at every zoom; a_style = (width in CSS px, dashed flag). The quad is one
// pixel wider than the line and the fragment shader fades the edge, so lines are smooth even
// without multisampling.
export const LINE_VS = `
attribute vec2 a_p0;
attribute vec2 a_p1;
attribute vec2 a_corner;
attribute vec4 a_color;
attribute vec2 a_style;
uniform vec2 u_center;
uniform vec2 u_scale;
uniform vec2 u_viewport;
uniform float u_dpr;
varying vec4 v_color;
varying float v_along;
varying float v_dash;
varying float v_edge;
varying float v_half;
void main() {
  vec2 half_vp = 0.5 * u_viewport;
  vec2 s0 = (a_p0 - u_center) * u_scale * half_vp;
  vec2 s1 = (a_p1 - u_center) * u_scale * half_vp;
  vec2 d = s1 - s0;
  float len = length(d);
  vec2 dir = len > 1e-4 ? d / len : vec2(1.0, 0.0);
  vec2 n = vec2(-dir.y, dir.x);
  float hw = 0.5 * a_style.x * u_dpr;
  float reach = hw + 1.0;
  vec2 s = mix(s0, s1, a_corner.x) + n * a_corner.y * reach + dir * (2.0 * a_corner.x - 1.0) * hw;
  gl_Position = vec4(s / half_vp, 0.0, 1.0);
  v_color = a_color;
  v_along = a_corner.x * len / u_dpr;
  v_dash = a_style.y;
  v_edge = a_corner.y * reach;
  v_half = hw;
}`;

export const LINE_FS = `
precision mediump float;
varying vec4 v_color;
varying float v_along;
varying float v_dash;
varying float v_edge;
varying float v_half;
void main() {
  if (v_dash > 0.5 && mod(v_along, 11.0) > 7.0) discard;
  float a = v_color.a * clamp(v_half - abs(v_edge) + 0.5, 0.0, 1.0);
  gl_FragColor = vec4(v_color.rgb * a, a);
}`;

// The CPU-splatted points (splat.js): a one-channel texture of per-pixel point counts, drawn
// over the screen tiles that have points. n points of opacity u_color.a cover a pixel as
// 1 - (1 - a)^n, the same as n blended GL points. The texture's rows are padded to whole words
// (u_uscale: shown width / texture width).
export const SPLAT_VS = `
attribute vec2 a_pos;
uniform float u_uscale;
varying vec2 v_uv;
void main() {
  v_uv = (0.5 * a_pos + 0.5) * vec2(u_uscale, 1.0);
  gl_Position = vec4(a_pos, 0.0, 1.0);
}`;

export const SPLAT_FS = `
precision mediump float;
uniform sampler2D u_counts;
uniform vec4 u_color;
varying vec2 v_uv;
void main() {
  float n = texture2D(u_counts, v_uv).r * 255.0;
  float a = 1.0 - pow(1.0 - u_color.a, n);
  gl_FragColor = vec4(u_color.rgb * a, a);
}`;

/** Binds `texture` to TEXTURE_2D for texel-exact reads: nearest filtering, clamped edges. */
export function bindExactTexture(gl, texture) {
  gl.bindTexture(gl.TEXTURE_2D, texture);
  for (const [p, v] of [
    [gl.TEXTURE_MIN_FILTER, gl.NEAREST],
    [gl.TEXTURE_MAG_FILTER, gl.NEAREST],
    [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE],
    [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE],
  ]) {
    gl.texParameteri(gl.TEXTURE_2D, p, v);
  }
}

/** Compiles and links a program; returns {program, attrib: {name: loc}, uniform: {name: loc}}. */
export function compile(gl, vs, fs) {
  const program = gl.createProgram();
  for (const [type, source] of [
    [gl.VERTEX_SHADER, vs],
    [gl.FRAGMENT_SHADER, fs],
  ]) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
      throw new Error(`shader: ${gl.getShaderInfoLog(shader)}`);
    }
    gl.attachShader(program, shader);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) {
    throw new Error(`shader link: ${gl.getProgramInfoLog(program)}`);
  }
  const info = { program, attrib: {}, uniform: {} };
  const na = gl.getProgramParameter(program, gl.ACTIVE_ATTRIBUTES);
  for (let i = 0; i < na; i++) {
    const name = gl.getActiveAttrib(program, i).name;
    info.attrib[name] = gl.getAttribLocation(program, name);
  }
  const nu = gl.getProgramParameter(program, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < nu; i++) {
    const name = gl.getActiveUniform(program, i).name;
    info.uniform[name] = gl.getUniformLocation(program, name);
  }
  return info;
}
