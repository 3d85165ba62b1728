// The WebGL renderer. Map positions live in GPU buffers, uploaded once per map version straight
// from the fetched Float32Arrays; the view (pan/zoom) is a uniform, so moving it only re-issues
// the draw calls. Draws, back to front: laser points (orange), the drawn segments (wide,
// translucent), the preview's S_a/S_b (red/blue), pose arrows (grey, blue in a correction), the
// fitted lines P_a/P_b (dashed). Each frame is timed up to a 1-pixel readPixels, which waits for
// the GPU to finish it.
//
// Laser points arrive once, in their robot's frame; after a correction only the poses change.
// They take one of two paths (`pointsPath`): "gpu", GL_POINTS placed by their pose in the vertex
// shader (the poses are a float texture), with a real GPU; "cpu", splat.js, on a software WebGL,
// where GL_POINTS costs ~0.6 us a point (300 ms for 500,000). The page URL's ?points=gpu|cpu
// overrides the choice. A WebGL without float textures in the vertex shader places the points on
// the CPU for the "gpu" path (`placedBy` says which).

import { frames, placePoints } from "./se2.js";
import { PointSplatter } from "./splat.js";
import {
  ARROW_VS,
  COLOUR_FS,
  LINE_FS,
  LINE_VS,
  POINT_FS,
  POINT_VS,
  SCAN_VS,
  bindExactTexture,
  compile,
} from "./shaders.js";

const BACKGROUND = [0xfb / 255, 0xfa / 255, 0xf7 / 255];
export const COLOURS = {
  observation: [0xf2 / 255, 0x8e / 255, 0x1c / 255, 0.55],
  pose: [0.29, 0.29, 0.29, 0.85],
  constrained: [0x1f / 255, 0x4f / 255, 0xd8 / 255, 1.0],
  a: [0xd6 / 255, 0x27 / 255, 0x28 / 255, 1.0],
  b: [0x1f / 255, 0x4f / 255, 0xd8 / 255, 1.0],
  // Fitted lines are darker than the points they were fitted to, so they show on top of them.
  fittedA: [0x9a / 255, 0x10 / 255, 0x14 / 255, 1.0],
  fittedB: [0x0c / 255, 0x2a / 255, 0x8a / 255, 1.0],
  highlightA: [0xd6 / 255, 0x27 / 255, 0x28 / 255, 0.8],
  highlightB: [0x1f / 255, 0x4f / 255, 0xd8 / 255, 0.8],
};

// An arrow one unit long from tail (-0.5, 0) to tip (0.5, 0): a shaft and a head.
const ARROW_SHAPE = new Float32Array([
  -0.5, -0.07, 0.1, -0.07, 0.1, 0.07, -0.5, -0.07, 0.1, 0.07, -0.5, 0.07, 0.05, -0.3, 0.5, 0.0,
  0.05, 0.3,
]);
const LINE_CORNERS = [
  [0, -1],
  [1, -1],
  [1, 1],
  [0, -1],
  [1, 1],
  [0, 1],
];
const LINE_FLOATS = 12; // p0 (2), p1 (2), corner (2), colour (4), style (2)
const ARROW_FLOATS = 6; // pose (x, y, theta, in-a-correction flag), corner (2)
const SOFTWARE = /SwiftShader|llvmpipe|softpipe|Software|Basic Render/i;

/** The renderer string of this browser's WebGL, from a throwaway context. */
function probeRenderer() {
  const gl = document.createElement("canvas").getContext("webgl");
  if (!gl) return "";
  const dbg = gl.getExtension("WEBGL_debug_renderer_info");
  const name = String(gl.getParameter(dbg ? dbg.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
  const lose = gl.getExtension("WEBGL_lose_context");
  if (lose) lose.loseContext();
  return name;
}

export class MapView {
  constructor(canvas) {
    this.canvas = canvas;
    this.renderer = probeRenderer();
    const software = SOFTWARE.test(this.renderer);
    const asked = new URLSearchParams(window.location.search).get("points");
    this.pointsPath = asked === "gpu" || asked === "cpu" ? asked : software ? "cpu" : "gpu";
    // Multisampling costs a software renderer 3-7 ms a frame; lines fade their own edges.
    const options = { antialias: !software, alpha: false, depth: false, premultipliedAlpha: true };
    this.gl = canvas.getContext("webgl2", options) || canvas.getContext("webgl", options);
    const gl = this.gl;
    if (!gl) throw new Error("this browser has no WebGL; hitl-slam's map view needs it");
    // Float textures readable by the vertex shader: WebGL 2, or WebGL 1 with OES_texture_float.
    this.webgl2 = typeof WebGL2RenderingContext !== "undefined" && gl instanceof WebGL2RenderingContext;
    const floats = this.webgl2 || gl.getExtension("OES_texture_float") !== null;
    this.placedBy = floats && gl.getParameter(gl.MAX_VERTEX_TEXTURE_IMAGE_UNITS) > 0 ? "shader" : "cpu";
    this.programs = {
      points: compile(gl, POINT_VS, POINT_FS),
      scans: this.placedBy === "shader" ? compile(gl, SCAN_VS, POINT_FS) : null,
      arrows: compile(gl, ARROW_VS, COLOUR_FS),
      lines: compile(gl, LINE_VS, LINE_FS),
    };
    this.splatter = new PointSplatter(gl);
    this.buffers = {
      points: gl.createBuffer(), // world points (when placed on the CPU)
      local: gl.createBuffer(), // robot-frame points (when placed by the shader)
      owner: gl.createBuffer(), // each point's pose index, as a float
      poses: gl.createBuffer(),
      under: gl.createBuffer(),
      over: gl.createBuffer(),
      highlightA: gl.createBuffer(),
      highlightB: gl.createBuffer(),
    };
    this.poseTexture = gl.createTexture();
    this.poseTextureSize = [1, 1];
    this.numPoints = 0;
    this.scans = null; // {points, offsets} in the robot frame, from setScans
    this.poses = new Float32Array(0); // (N, 3) of the current map
    this.constrained = new Uint8Array(0);
    this.poseSpacing = 0.1; // median distance between consecutive poses [m]
    this.shownPoses = 0;
    this.poseStep = 0; // every how many poses an arrow is drawn (0: rebuild)
    this.numHighlights = [0, 0];
    this.numLineVertices = { under: 0, over: 0 };
    this.enabled = [];
    this.dpr = 1;
    this.pixel = new Uint8Array(4);
    this.frames = []; // recent frame durations [ms], up to the readPixels sync
    this.splats = []; // of which counting the points on the CPU [ms] (the "cpu" path)
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.disable(gl.DEPTH_TEST);
  }

  /** Matches the drawing buffer to the canvas's CSS size times devicePixelRatio (crisp). */
  resize() {
    this.dpr = window.devicePixelRatio || 1;
    const rect = this.canvas.getBoundingClientRect();
    const w = Math.max(1, Math.round(rect.width * this.dpr));
    const h = Math.max(1, Math.round(rect.height * this.dpr));
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
    return [rect.width, rect.height];
  }

  /**
   * The map's scans, once: every point in its robot's frame (P*2 float32) and the per-pose
   * offsets (N+1 int32: pose i's points are points[2 offsets[i] .. 2 offsets[i + 1]]).
   */
  setScans(points, offsets) {
    const gl = this.gl;
    this.scans = { points, offsets };
    this.numPoints = points.length >>> 1;
    if (this.pointsPath === "cpu") {
      this.splatter.setScans(points, offsets);
    } else if (this.placedBy === "shader") {
      const owner = new Float32Array(this.numPoints);
      for (let p = 0; p + 1 < offsets.length; p++) owner.fill(p, offsets[p], offsets[p + 1]);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.local);
      gl.bufferData(gl.ARRAY_BUFFER, points, gl.STATIC_DRAW);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.owner);
      gl.bufferData(gl.ARRAY_BUFFER, owner, gl.STATIC_DRAW);
    }
  }

  /** A map version: its poses (N*3 float32) and which are constrained; the scans follow them. */
  setPoses(poses, constrained) {
    const gl = this.gl;
    if (this.pointsPath === "cpu") {
      this.splatter.setPoses(poses);
    } else if (this.placedBy === "shader") {
      this._uploadPoseTexture(poses);
    } else if (this.scans) {
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.points);
      gl.bufferData(gl.ARRAY_BUFFER, placePoints(this.scans.points, this.scans.offsets, poses), gl.STATIC_DRAW);
    }
    this.poses = poses;
    this.constrained = constrained;
    const n = poses.length / 3;
    const steps = [];
    for (let i = 1; i < n; i += Math.max(1, Math.floor(n / 2000))) {
      steps.push(Math.hypot(poses[3 * i] - poses[3 * i - 3], poses[3 * i + 1] - poses[3 * i - 2]));
    }
    steps.sort((p, q) => p - q);
    this.poseSpacing = steps.length ? Math.max(steps[steps.length >> 1], 1e-3) : 0.1;
    this.poseStep = 0;
  }

  /** The poses as (x, y, cos, sin) float texels, rows of up to 2048 (texture unit 1). */
  _uploadPoseTexture(poses) {
    const gl = this.gl;
    const n = Math.max(1, poses.length / 3);
    const width = Math.min(n, 2048);
    const height = Math.ceil(n / width);
    const texels = new Float32Array(4 * width * height);
    texels.set(frames(poses)); // x, y, cos, sin per pose
    gl.activeTexture(gl.TEXTURE1);
    bindExactTexture(gl, this.poseTexture);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
    const internal = this.webgl2 ? gl.RGBA32F : gl.RGBA;
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, width, height, 0, gl.RGBA, gl.FLOAT, texels);
    gl.activeTexture(gl.TEXTURE0);
    this.poseTextureSize = [width, height];
  }

  /** Which poses are in a correction changed (history), not the poses themselves. */
  setConstrained(constrained) {
    this.constrained = constrained;
    this.poseStep = 0;
  }

  /** S_a and S_b of the preview as world positions (float32 x, y pairs); empty arrays clear. */
  setHighlights(a, b) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.highlightA);
    gl.bufferData(gl.ARRAY_BUFFER, a, gl.DYNAMIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.highlightB);
    gl.bufferData(gl.ARRAY_BUFFER, b, gl.DYNAMIC_DRAW);
    this.numHighlights = [a.length >>> 1, b.length >>> 1];
  }

  /**
   * Overlay lines, [{p0: [x, y], p1: [x, y], colour: [r, g, b, a], width: px, dashed}] each:
   * `under` between the laser points and the highlighted S_a / S_b (the drawn strokes, so the
   * selection shows on top of them), `over` above everything (fitted lines).
   */
  setLines(under, over) {
    const gl = this.gl;
    for (const [layer, lines] of [
      ["under", under],
      ["over", over],
    ]) {
      const data = new Float32Array(lines.length * 6 * LINE_FLOATS);
      let k = 0;
      for (const line of lines) {
        for (const [t, side] of LINE_CORNERS) {
          data.set([...line.p0, ...line.p1, t, side, ...line.colour, line.width, line.dashed ? 1 : 0], k);
          k += LINE_FLOATS;
        }
      }
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers[layer]);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.DYNAMIC_DRAW);
      this.numLineVertices[layer] = lines.length * 6;
    }
  }

  // Zoomed out, arrows closer than about their length are thinned to every k-th pose (k a
  // power of two, so the choice is stable while zooming); poses in a correction always show.
  // Each shown pose is written out as the arrow's 9 corners (x, y, theta, flag, corner): plain
  // triangles, because instanced draws are several times slower on software renderers.
  _updatePoseInstances(step) {
    const n = this.poses.length / 3;
    const corners = ARROW_SHAPE.length / 2;
    const data = new Float32Array(n * corners * ARROW_FLOATS);
    let k = 0;
    let m = 0;
    for (let i = 0; i < n; i++) {
      const flagged = this.constrained[i] === 1;
      if (i % step !== 0 && !flagged) continue;
      const x = this.poses[3 * i];
      const y = this.poses[3 * i + 1];
      const t = this.poses[3 * i + 2];
      for (let c = 0; c < corners; c++) {
        data[k++] = x;
        data[k++] = y;
        data[k++] = t;
        data[k++] = flagged ? 1 : 0;
        data[k++] = ARROW_SHAPE[2 * c];
        data[k++] = ARROW_SHAPE[2 * c + 1];
      }
      m++;
    }
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.poses);
    gl.bufferData(gl.ARRAY_BUFFER, data.subarray(0, k), gl.STATIC_DRAW);
    this.shownPoses = m;
    this.poseStep = step;
  }

  _attrib(info, name, buffer, size, stride = 0, offset = 0) {
    const gl = this.gl;
    const loc = info.attrib[name];
    if (loc === undefined || loc < 0) return;
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, size, gl.FLOAT, false, stride, offset);
    this.enabled.push(loc);
  }

  _release() {
    for (const loc of this.enabled) this.gl.disableVertexAttribArray(loc);
    this.enabled = [];
  }

  _uniforms(info, center, scale, viewport) {
    const gl = this.gl;
    gl.useProgram(info.program);
    gl.uniform2fv(info.uniform.u_center, center);
    gl.uniform2fv(info.uniform.u_scale, scale);
    if (info.uniform.u_viewport) gl.uniform2fv(info.uniform.u_viewport, viewport);
    if (info.uniform.u_dpr) gl.uniform1f(info.uniform.u_dpr, this.dpr);
  }

  _drawLines(layer, center, scale, viewport) {
    if (this.numLineVertices[layer] === 0) return;
    const ln = this.programs.lines;
    const buffer = this.buffers[layer];
    this._uniforms(ln, center, scale, viewport);
    const stride = LINE_FLOATS * 4;
    this._attrib(ln, "a_p0", buffer, 2, stride, 0);
    this._attrib(ln, "a_p1", buffer, 2, stride, 8);
    this._attrib(ln, "a_corner", buffer, 2, stride, 16);
    this._attrib(ln, "a_color", buffer, 4, stride, 24);
    this._attrib(ln, "a_style", buffer, 2, stride, 40);
    this.gl.drawArrays(this.gl.TRIANGLES, 0, this.numLineVertices[layer]);
    this._release();
  }

  /** Draws everything for `camera`; returns the frame time [ms] up to the GPU sync. */
  render(camera) {
    const start = performance.now();
    const gl = this.gl;
    const dpr = this.dpr;
    const { center, scale } = camera.uniforms();
    const viewport = [this.canvas.width, this.canvas.height];
    gl.viewport(0, 0, viewport[0], viewport[1]);
    gl.clearColor(...BACKGROUND, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);

    // Laser points: about 2 cm wide, but never under 1 or over 3 CSS pixels.
    const pointPx = Math.min(3, Math.max(1, camera.scale * 0.02)) * dpr;
    const pts = this.programs.points;
    if (this.numPoints > 0 && this.pointsPath === "cpu") {
      const k = camera.scale * dpr;
      this.splatter.draw(camera.cx, camera.cy, k, pointPx, COLOURS.observation, ...viewport);
      this.splats.push(this.splatter.lastCpuMs);
      if (this.splats.length > 600) this.splats.splice(0, this.splats.length - 600);
    } else if (this.numPoints > 0 && this.placedBy === "shader") {
      const sc = this.programs.scans;
      this._uniforms(sc, center, scale, viewport);
      this._attrib(sc, "a_local", this.buffers.local, 2);
      this._attrib(sc, "a_pose", this.buffers.owner, 1);
      gl.activeTexture(gl.TEXTURE1);
      gl.bindTexture(gl.TEXTURE_2D, this.poseTexture);
      gl.activeTexture(gl.TEXTURE0);
      gl.uniform1i(sc.uniform.u_poses, 1);
      gl.uniform2fv(sc.uniform.u_poses_size, this.poseTextureSize);
      gl.uniform1f(sc.uniform.u_size, pointPx);
      gl.uniform1f(sc.uniform.u_round, 0);
      gl.uniform4fv(sc.uniform.u_color, COLOURS.observation);
      gl.drawArrays(gl.POINTS, 0, this.numPoints);
      this._release();
    } else if (this.numPoints > 0) {
      this._uniforms(pts, center, scale, viewport);
      this._attrib(pts, "a_pos", this.buffers.points, 2);
      gl.uniform1f(pts.uniform.u_size, pointPx);
      gl.uniform1f(pts.uniform.u_round, 0);
      gl.uniform4fv(pts.uniform.u_color, COLOURS.observation);
      gl.drawArrays(gl.POINTS, 0, this.numPoints);
      this._release();
    }
    this._drawLines("under", center, scale, viewport);

    // The preview's S_a / S_b above the drawn strokes, larger and nearly opaque.
    const hsize = Math.min(3.5, Math.max(2.5, camera.scale * 0.015)) * dpr;
    for (const [k, buffer, colour] of [
      [0, this.buffers.highlightA, COLOURS.highlightA],
      [1, this.buffers.highlightB, COLOURS.highlightB],
    ]) {
      if (this.numHighlights[k] === 0) continue;
      this._uniforms(pts, center, scale, viewport);
      this._attrib(pts, "a_pos", buffer, 2);
      gl.uniform1f(pts.uniform.u_size, hsize);
      gl.uniform1f(pts.uniform.u_round, 1);
      gl.uniform4fv(pts.uniform.u_color, colour);
      gl.drawArrays(gl.POINTS, 0, this.numHighlights[k]);
      this._release();
    }

    // Pose arrows, 5 to 14 CSS pixels long: as long as the spacing between poses allows.
    const n = this.poses.length / 3;
    if (n > 0) {
      const spacingPx = this.poseSpacing * camera.scale;
      const arrowPx = Math.min(14, Math.max(5, 1.6 * spacingPx));
      let step = 1;
      while (step < n && step * spacingPx < 1.2 * arrowPx) step *= 2;
      if (step !== this.poseStep) this._updatePoseInstances(step);
      const arr = this.programs.arrows;
      this._uniforms(arr, center, scale, viewport);
      gl.uniform1f(arr.uniform.u_arrow, arrowPx * dpr);
      gl.uniform4fv(arr.uniform.u_plain, COLOURS.pose);
      gl.uniform4fv(arr.uniform.u_constrained, COLOURS.constrained);
      this._attrib(arr, "a_pose", this.buffers.poses, 4, ARROW_FLOATS * 4, 0);
      this._attrib(arr, "a_local", this.buffers.poses, 2, ARROW_FLOATS * 4, 16);
      gl.drawArrays(gl.TRIANGLES, 0, this.shownPoses * (ARROW_SHAPE.length / 2));
      this._release();
    }

    this._drawLines("over", center, scale, viewport);

    // A 1-pixel read waits for the GPU to finish the frame, so the time below is the real
    // cost of drawing, not just of queueing the commands.
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, this.pixel);
    const ms = performance.now() - start;
    this.frames.push(ms);
    if (this.frames.length > 600) this.frames.splice(0, this.frames.length - 600);
    return ms;
  }
}
