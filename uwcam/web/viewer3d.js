// The latest range map as a point cloud in WebGL: camera frame (x right, y down, z forward),
// each point coloured by the image. Drag to orbit about the cloud's centre, wheel to zoom.

const VERTEX = `
attribute vec3 position;
attribute vec3 colour;
uniform mat4 transform;
uniform float size;
varying vec3 v_colour;
void main() {
  gl_Position = transform * vec4(position, 1.0);
  gl_PointSize = size;
  v_colour = colour;
}`;

const FRAGMENT = `
precision mediump float;
varying vec3 v_colour;
void main() { gl_FragColor = vec4(v_colour, 1.0); }`;

function multiply(a, b) {
  const out = new Float32Array(16);
  for (let i = 0; i < 4; i++) {
    for (let j = 0; j < 4; j++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + j] * b[i * 4 + k];
      out[i * 4 + j] = s;
    }
  }
  return out;
}

function perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
  return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0]);
}

function rotationX(a) {
  const c = Math.cos(a), s = Math.sin(a);
  return new Float32Array([1, 0, 0, 0, 0, c, s, 0, 0, -s, c, 0, 0, 0, 0, 1]);
}

function rotationY(a) {
  const c = Math.cos(a), s = Math.sin(a);
  return new Float32Array([c, 0, -s, 0, 0, 1, 0, 0, s, 0, c, 0, 0, 0, 0, 1]);
}

function translation(x, y, z) {
  return new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, x, y, z, 1]);
}

export class PointCloudView {
  constructor(canvas) {
    this.canvas = canvas;
    const gl = canvas.getContext("webgl", { preserveDrawingBuffer: true });
    this.gl = gl;
    this.yaw = 0.5; this.pitch = -0.5; this.distance = 4; this.centre = [0, 0, 2]; this.count = 0;
    if (!gl) { this.fallback("WebGL is not available in this browser: the 3-D view needs it"); return; }
    const program = gl.createProgram();
    for (const [type, source] of [[gl.VERTEX_SHADER, VERTEX], [gl.FRAGMENT_SHADER, FRAGMENT]]) {
      const shader = gl.createShader(type);
      gl.shaderSource(shader, source);
      gl.compileShader(shader);
      gl.attachShader(program, shader);
    }
    gl.linkProgram(program);
    this.program = program;
    this.positions = gl.createBuffer();
    this.colours = gl.createBuffer();
    this.scratch = document.createElement("canvas");
    let drag = null;
    canvas.addEventListener("pointerdown", (e) => { drag = { x: e.clientX, y: e.clientY }; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener("pointermove", (e) => {
      if (!drag) return;
      this.yaw += (e.clientX - drag.x) * 0.01;
      this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + (e.clientY - drag.y) * 0.01));
      drag = { x: e.clientX, y: e.clientY };
      this.draw();
    });
    canvas.addEventListener("pointerup", () => { drag = null; });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.distance = Math.max(0.2, Math.min(100, this.distance * Math.exp(e.deltaY * 0.001)));
      this.draw();
    }, { passive: false });
  }

  fallback(text) {
    const ctx = this.canvas.getContext("2d");
    if (ctx) { ctx.fillStyle = "#fff"; ctx.fillText(text, 10, 20); }
  }

  update(frame, bitmap, hello) {
    if (!this.gl) return;
    const intr = hello?.intrinsics;
    if (!intr) { this.fallback("no camera intrinsics in the calibration profile: no 3-D view"); return; }
    const r = frame.range;
    const stride = Math.max(1, Math.round(Math.sqrt((r.width * r.height) / 120000)));
    let pixels = null, cw = 0, ch = 0;
    if (bitmap) {
      cw = bitmap.width; ch = bitmap.height;
      this.scratch.width = cw; this.scratch.height = ch;
      const ctx = this.scratch.getContext("2d", { willReadFrequently: true });
      ctx.drawImage(bitmap, 0, 0);
      pixels = ctx.getImageData(0, 0, cw, ch).data;
    }
    const w = frame.header.image_width, h = frame.header.image_height;
    const positions = [], colours = [];
    let sx = 0, sy = 0, sz = 0;
    for (let v = 0; v < r.height; v += stride) {
      for (let u = 0; u < r.width; u += stride) {
        const value = r.data[v * r.width + u];
        if (value >= r.invalid_base) continue;
        const px = u * r.step, py = v * r.step;
        const x = (px - intr.cx) / intr.fx, y = (py - intr.cy) / intr.fy;
        const scale = (value / 1000) / Math.hypot(x, y, 1);  // range is along the ray
        const p = [x * scale, y * scale, scale];
        positions.push(...p);
        sx += p[0]; sy += p[1]; sz += p[2];
        if (pixels) {
          const i = (Math.min(ch - 1, Math.floor((py / h) * ch)) * cw + Math.min(cw - 1, Math.floor((px / w) * cw))) * 4;
          colours.push(pixels[i] / 255, pixels[i + 1] / 255, pixels[i + 2] / 255);
        } else colours.push(0.8, 0.8, 0.8);
      }
    }
    this.count = positions.length / 3;
    if (this.count) this.centre = [sx / this.count, sy / this.count, sz / this.count];
    if (!this.placed && this.count) { this.distance = Math.max(1, this.centre[2] * 1.6); this.placed = true; }
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.positions);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(positions), gl.DYNAMIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.colours);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(colours), gl.DYNAMIC_DRAW);
    this.draw();
  }

  draw() {
    const gl = this.gl;
    if (!gl) return;
    const canvas = this.canvas;
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.clearColor(0.03, 0.07, 0.1, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    if (!this.count) return;
    gl.useProgram(this.program);
    // Camera frame has y down: flip y so that the seabed is below. Orbit about the cloud's centre.
    const [cx, cy, cz] = this.centre;
    let m = translation(-cx, -cy, -cz);
    m = multiply(new Float32Array([1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]), m);
    m = multiply(rotationY(this.yaw), m);
    m = multiply(rotationX(this.pitch), m);
    m = multiply(translation(0, 0, -this.distance), m);
    m = multiply(perspective(0.9, canvas.width / canvas.height, 0.05, 500), m);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.program, "transform"), false, m);
    gl.uniform1f(gl.getUniformLocation(this.program, "size"), 2.0);
    for (const [name, buffer] of [["position", this.positions], ["colour", this.colours]]) {
      const location = gl.getAttribLocation(this.program, name);
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, 3, gl.FLOAT, false, 0, 0);
    }
    gl.drawArrays(gl.POINTS, 0, this.count);
  }
}
