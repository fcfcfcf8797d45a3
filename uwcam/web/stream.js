// The daemon's view stream (WS api/v1/view): connect, decode frames, acknowledge painted ones.
// Message layout: see uwcam/api/view.py.

const F16 = (() => {
  // float16 bit pattern → float32, for all 65536 patterns (σ planes are decoded through it).
  const table = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, f = h & 0x3ff;
    table[h] = e === 0 ? s * Math.pow(2, -14) * (f / 1024)
      : e === 31 ? (f ? NaN : s * Infinity)
      : s * Math.pow(2, e - 15) * (1 + f / 1024);
  }
  return table;
})();

export function float16(bits) {
  return F16[bits];
}

export function decodeFrame(buffer) {
  const view = new DataView(buffer);
  const magic = String.fromCharCode(...new Uint8Array(buffer, 0, 4));
  if (magic !== "UWV1") throw new Error(`unexpected stream message (${magic})`);
  const length = view.getUint32(4, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 8, length)));
  const frame = { header, number: header.frame, captureMs: header.capture_time_ns / 1e6 };
  for (const s of header.sections) {
    if (s.name === "range") frame.range = { data: new Uint16Array(buffer, s.offset, s.width * s.height), ...s };
    else if (s.name === "sigma") frame.sigma = { data: new Uint16Array(buffer, s.offset, s.width * s.height), ...s };
    else if (s.name === "colour") frame.colour = { blob: new Blob([new Uint8Array(buffer, s.offset, s.length)], { type: s.mime }), ...s };
  }
  return frame;
}

// Range in metres at image pixel (x, y) of a frame, or null with the reason code when invalid.
// x, y: the image pixel whose value it is (the map holds every step-th pixel).
export function sample(frame, x, y) {
  const r = frame.range;
  const col = Math.min(r.width - 1, Math.max(0, Math.floor(x / r.step)));
  const row = Math.min(r.height - 1, Math.max(0, Math.floor(y / r.step)));
  const i = row * r.width + col;
  x = col * r.step; y = row * r.step;
  const v = r.data[i];
  const s = frame.sigma;
  const j = Math.min(s.height - 1, Math.max(0, Math.floor(y / s.step))) * s.width
    + Math.min(s.width - 1, Math.max(0, Math.floor(x / s.step)));
  if (v >= r.invalid_base) return { range: null, reason: v - r.invalid_base, x, y };
  return { range: v / 1000, sigma: F16[s.data[j]] / 1000, reason: 0, x, y };
}

export function centreAndMinimum(range) {
  // Centre: median of valid ranges in the middle 10 % of the image. Minimum: the smallest median
  // of the blocks (about 1/32 of the image width) that are at least half valid — a median over a
  // block is robust to the noisy pixels of a dark corner, which must not read as an obstacle.
  // Blocks are sampled on a grid of at most ~20 000 pixels so that this costs little at any size.
  const { data, width, height, invalid_base: base } = range;
  const stride = Math.max(1, Math.floor(Math.sqrt((width * height) / 20000)));
  const block = Math.max(4 * stride, Math.round(width / 32));
  const median = (values) => {
    const sorted = Uint16Array.from(values).sort();
    return sorted[sorted.length >> 1] / 1000;
  };
  let minimum = null;
  for (let by = 0; by < height; by += block) {
    for (let bx = 0; bx < width; bx += block) {
      const values = [];
      let seen = 0;
      for (let y = by; y < Math.min(by + block, height); y += stride) {
        for (let x = bx; x < Math.min(bx + block, width); x += stride) {
          seen++;
          const v = data[y * width + x];
          if (v < base) values.push(v);
        }
      }
      if (values.length * 2 < seen) continue;
      const m = median(values);
      if (minimum === null || m < minimum) minimum = m;
    }
  }
  const centre = [];
  const x0 = Math.floor(width * 0.45), x1 = Math.ceil(width * 0.55), y0 = Math.floor(height * 0.45), y1 = Math.ceil(height * 0.55);
  for (let y = y0; y < y1; y++) {
    for (let x = x0; x < x1; x++) {
      const v = data[y * width + x];
      if (v < base) centre.push(v);
    }
  }
  return { centre: centre.length ? median(centre) : null, minimum };
}

export function wsUrl(path) {
  const url = new URL(path, document.baseURI);
  url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
  return url.href;
}

// Keeps a view stream open (reconnecting with backoff) and hands each decoded frame to onFrame.
// The caller calls ack(number) once it has painted a frame.
export class ViewStream {
  // step: a fixed resolution step (1, 2, 4); or width(): the pixels the range map is drawn across
  // now, from which the daemon picks the coarsest step that still fills them (see setWidth).
  constructor({ step = null, width = null, colour = true, onHello, onFrame, onState }) {
    Object.assign(this, { step, width, colour, onHello, onFrame, onState });
    this.retry = 500;
    this.connect();
  }

  drawnWidth() {
    return Math.max(1, Math.min(16384, Math.ceil(this.width ? this.width() : 640)));
  }

  connect() {
    const resolution = this.step ? `step=${this.step}` : `width=${(this.sentWidth = this.drawnWidth())}`;
    const ws = new WebSocket(wsUrl(`api/v1/view?${resolution}&colour=${this.colour}`));
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => { this.retry = 500; this.onState?.("connected"); };
    ws.onmessage = (event) => {
      if (typeof event.data === "string") {
        const message = JSON.parse(event.data);
        if (message.type === "hello") this.onHello?.(message);
        return;
      }
      this.onFrame(decodeFrame(event.data));
    };
    ws.onclose = () => {
      this.onState?.("disconnected");
      setTimeout(() => this.connect(), this.retry);
      this.retry = Math.min(this.retry * 2, 5000);
    };
  }

  // The page's layout changed: tell the daemon how wide the range map is drawn now.
  setWidth() {
    if (this.step || this.ws.readyState !== WebSocket.OPEN) return;
    const width = this.drawnWidth();
    if (width !== this.sentWidth) { this.sentWidth = width; this.ws.send(JSON.stringify({ width })); }
  }

  ack(number) {
    if (this.ws.readyState === WebSocket.OPEN) this.ws.send(JSON.stringify({ ack: number }));
  }
}
