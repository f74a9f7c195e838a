// face-retarget 3D playback viewer: a blendshape rig as three.js morph targets.
//
// Sent once: the mesh, neutral (V,3) f32, faces (F,3) u32 and deltas (K,V,3) f32 packed in one
// blob (dashboard/payloads.py, decodeGeometry below), fetched from `geometry_url` (one copy on
// the server for every page, cached by the browser under its content key) or, without that
// route, inline in `geometry`; the weight track (T,K) f32 the same way (a blob fetched from
// `track_url`, decodeTrack below, or inline in `track`, a bokeh ndarray buffer); the marker
// layout / marker track as binary bokeh buffers.
// Per frame nothing travels while playing: the browser plays the track at `fps` on a
// clock shared by every viewer in the same `sync_group`; the group's first viewer writes
// `frame` back to Python at most every `sync_interval` seconds (0 = only when playback
// stops, when every viewer writes its final frame).
//
// Mesh:    position = neutral + sum_k w_k delta_k
//          blend "gpu": three.js morph targets (morphAttributes, morphTargetsRelative), the
//          vertex shader loops over all K targets held in a texture;
//          blend "cpu": the same sum in JS, uploaded per frame. Streamed weights (a live stream)
//          update the buffers incrementally, position += (w_k - b_k) delta_k (normals alike)
//          for the shapes whose weight changed since the buffers were blended with b; a change
//          too small to see is deferred while the deferred shapes' bound on the error,
//          sum_k |w_k - b_k| max|delta_k| (per coordinate), stays under DEFER_TOL x the mesh's
//          size (and sum_k |w_k - b_k| max|dn_k| under DEFER_TOL_NORMAL). Re-blended from scratch
//          (the dense sum over non-zero w_k, as a track frame is) every REBLEND_EVERY updates and
//          when as many shapes changed as are non-zero, so float32 rounding cannot drift.
//          window.__faceRetargetFullBlend = true: every frame from scratch (bench_live_page.py's ref).
//          "auto" picks cpu on a software WebGL (SwiftShader, llvmpipe), where the "GPU" is
//          the CPU and the generic shader fetches every target for every vertex.
// Normals: n(w) = n0 + sum_k w_k (n_k - n0), renormalised in the shader, with n_k the
//          area-weighted vertex normals of neutral + delta_k, welded over UV seams
//          (computed here once, so normals cost no payload).
// Offsets (optional): offsets (V,3) f32, a per-vertex displacement added after the blend
//          (fine-scale detail of a dense transfer, not in the rig), sent whenever it changes
//          and nothing else with it. While set, the mesh is blended in JS (a gpu-blended mesh
//          swaps its morph targets out for the JS buffers, kept for switching back), and the
//          normals are the exact area-weighted vertex normals of the final positions, so the
//          offsets show in the shading. Cleared (null), the previous blend comes back as it was.
// Markers: p_m = sum_j b_mj (neutral[v_mj] + sum_k w_k delta_k[v_mj] + offset[v_mj]) on the
//          CPU for the M layout markers (M*3*K multiply-adds per frame), or a (T,M,3) marker track.
// Normal map (optional): uvs (V,2) f32 once, normal_map (H,W,3) u8 when it changes, decoded
//          n = 2 rgb/255 - 1 by three's MeshStandardMaterial (ObjectSpaceNormalMap by default:
//          the map's normal replaces the vertex normal per pixel). A normal map forces the
//          standard material, also when shading is "fast" (per-vertex lighting cannot use it).
// Picking (pick_mode "vertex"): a three.js Raycaster against the mesh as shown (cpu blend:
//          the blended buffer; gpu: three's raycast applies the morph influences on the
//          CPU), then the hit triangle's vertex nearest to the hit point, its position
//          recomputed here from the weights shown (plus its offset, when offsets are set).
//          A click sets `picked`; a drag sets `dragged` with the end point in the camera
//          plane through the start point.

const GROUPS = (window.__faceRetargetGroups = window.__faceRetargetGroups || new Map());
const REGISTRY = (window.__faceRetarget = window.__faceRetarget || { viewers: {} });
const STATS = (window.__faceRetargetStats = window.__faceRetargetStats || { viewers: {} });
if (!STATS.reset) {
  STATS.reset = () => {
    for (const s of Object.values(STATS.viewers)) {
      s.renders = 0; s.renderMs = 0; s.framesShown = 0; s.framesSkipped = 0;
      // the streamed path's profile (drawStreamed, blendCpu, the message handler)
      s.streamed = 0; s.messageMs = 0; s.streamDraws = 0; s.streamDrawMs = 0;
      s.blendMs = 0; s.fullBlends = 0; s.incrementalBlends = 0; s.blendShapes = 0; s.deferredShapes = 0;
      for (const k of Object.keys(s)) if (k.startsWith("draws@")) s[k] = 0; // streamed draws per render scale
      s.t0 = performance.now();
    }
  };
}

const RIGHT_ANGLE = Math.PI / 2;
const REBLEND_EVERY = 60; // incremental JS blends between two blends from scratch (drift bound)
const DEFER_TOL = 1e-4;         // streamed blend: deferred changes move a coordinate < this x size
const DEFER_TOL_NORMAL = 1e-3;  // ... and a normal's coordinate < this (normals are unit vectors)
const DRAG_PX = 4; // a pointer that moves less than this between down and up is a click
// Streamed drawing keeps up by drawing fewer pixels, as games do: a drawn frame's cost is the time
// from its animation frame to the next one (the page's main thread waits there for the GPU to
// draw the canvases: software WebGL reads them back); when the frames a view drew cost more than
// STREAM_FRAME_MS (+3 %) on average, the next render scale of RENDER_SCALES is used (the view says so),
// and one step back up after SCALE_UP_WINDOWS windows in a row well within it. Every frame drawn
// is a new frame of the stream, at that resolution. (SwiftShader's draw of the two live meshes is
// most of a frame here; docs/live.md.)
const STREAM_FRAME_MS = 1000 / 30;
const RENDER_SCALES = [1, 0.75, 0.5];
const SCALE_WINDOW = 15;      // streamed draws per decision
const SCALE_UP_WINDOWS = 4;   // windows in a row under 0.6 x STREAM_FRAME_MS before scaling back up

// The render scale step after a window of streamed draws: `frameMs` their mean cost, `good` the
// windows in a row that had headroom. Returns [step, good].
function nextScaleStep(step, frameMs, good) {
  if (frameMs > 1.03 * STREAM_FRAME_MS) return [Math.min(step + 1, RENDER_SCALES.length - 1), 0];
  if (frameMs < 0.6 * STREAM_FRAME_MS) {
    good += 1;
    if (step > 0 && good >= SCALE_UP_WINDOWS) return [step - 1, 0];
    return [step, good];
  }
  return [step, 0];
}
REGISTRY.nextScaleStep = nextScaleStep; // the streamed drawing's resolution rule (tested alone)
REGISTRY.renderScales = RENDER_SCALES;

// ---------------------------------------------------------------------------------------
// How long after a pause the echoes of frames reported while playing are still ignored (ms): a
// user's own seek to one of those frames this soon after pausing is ignored too (the views and
// the slider then stay on the frame the page stopped on).
const ECHO_AFTER_STOP_MS = 1000;

// A playback clock shared by the viewers of one sync group (or private to one viewer).
class Clock {
  constructor(name) {
    this.name = name;
    this.members = new Set();
    this.frame = 0;
    this.playing = false;
    this.fps = 30;
    this.loop = true;
    this.t0 = 0;
    this.f0 = 0;
    this.raf = null;
    this.recent = []; // [frame, time] reported to Python lately: their echoes are ignored
    this.stoppedAt = -Infinity; // when playback last stopped (performance.now())
    this.camera = { azimuth: 0, elevation: 0, zoom: 1, panX: 0, panY: 0 };
  }
  get nFrames() {
    let n = 1;
    for (const m of this.members) n = Math.max(n, m.nFrames);
    return n;
  }
  join(v) { this.members.add(v); }
  // The shared zoom's range: no member's camera may enter its mesh's bounding sphere (the wheel
  // took the camera inside the target, the view went empty), at most 10x away.
  zoomRange() {
    let lo = 0.1;
    for (const m of this.members) lo = Math.max(lo, m.minZoom());
    return [lo, Math.max(lo, 10)];
  }
  setZoom(z) {
    const [lo, hi] = this.zoomRange();
    this.camera.zoom = Math.min(Math.max(z, lo), hi);
    this.cameraChanged();
  }
  leave(v) {
    this.members.delete(v);
    if (!this.members.size) {
      this.stopLoop();
      if (this.name) GROUPS.delete(this.name);
    }
  }
  clamp(f) {
    const n = this.nFrames;
    f = Math.round(Number(f) || 0);
    return Math.min(Math.max(f, 0), n - 1);
  }
  remember(f) {
    const now = performance.now();
    this.recent.push([f, now]);
    this.recent = this.recent.filter(([, t]) => now - t < 2000);
  }
  isEcho(f) {
    const now = performance.now();
    return this.recent.some(([g, t]) => g === f && now - t < 2000);
  }
  // A frame from Python that is only the echo of one this page reported while it played: stale
  // while playing, and for ECHO_AFTER_STOP_MS after it stopped too -- the server's echo of a
  // frame reported just before the pause can reach the page after the pause (the two cross),
  // and seeking to it put the views a frame behind the Frame slider, which had the frame the
  // page stopped on (seen in the browser test of Play, ~1 run in 10 on a loaded machine).
  isStaleEcho(f) {
    if (!this.playing && performance.now() - this.stoppedAt > ECHO_AFTER_STOP_MS) return false;
    return this.isEcho(f);
  }
  seek(f) {
    this.frame = this.clamp(f);
    if (this.playing) { this.t0 = performance.now(); this.f0 = this.frame; }
    for (const m of this.members) m.showFrame(this.frame, false);
  }
  setFps(fps) {
    if (!(fps > 0)) return;
    if (this.playing) { this.f0 = this.frame; this.t0 = performance.now(); }
    this.fps = fps;
  }
  play(on) {
    on = Boolean(on);
    if (on === this.playing) return;
    this.playing = on;
    if (on) {
      if (this.frame >= this.nFrames - 1 && !this.loop) this.frame = 0;
      this.t0 = performance.now();
      this.f0 = this.frame;
      for (const m of this.members) m.playbackStarted();
      this.startLoop();
    } else {
      this.stopLoop();
      this.stoppedAt = performance.now();
      for (const m of this.members) m.playbackStopped(this.frame);
    }
  }
  startLoop() {
    if (this.raf !== null) return;
    const step = (now) => {
      this.raf = null;
      if (!this.playing) return;
      this.tick(now);
      if (this.playing) this.raf = requestAnimationFrame(step);
    };
    this.raf = requestAnimationFrame(step);
  }
  stopLoop() {
    if (this.raf !== null) cancelAnimationFrame(this.raf);
    this.raf = null;
  }
  tick(now) {
    const n = this.nFrames;
    let f = this.f0 + Math.floor(((now - this.t0) / 1000) * this.fps + 1e-6);
    let ended = false;
    if (f >= n) {
      if (this.loop) {
        f = f % n;
        this.t0 = now; this.f0 = f;
      } else {
        f = n - 1;
        ended = true;
      }
    }
    if (f !== this.frame) {
      this.frame = f;
      for (const m of this.members) m.showFrame(f, true);
    }
    if (ended) this.play(false);
  }
  cameraChanged() { for (const m of this.members) m.updateCamera(); }
}

function clockFor(name) {
  if (!name) return new Clock("");
  if (!GROUPS.has(name)) GROUPS.set(name, new Clock(name));
  return GROUPS.get(name);
}

// ---------------------------------------------------------------------------------------
function asF32(a) {
  // bokeh decodes ndarrays to typed-array subclasses; three wants plain typed arrays
  if (a == null) return null;
  if (a instanceof Float32Array && a.constructor === Float32Array) return a;
  return Float32Array.from(a);
}
function asU32(a) {
  if (a == null) return null;
  return a instanceof Uint32Array && a.constructor === Uint32Array ? a : Uint32Array.from(a);
}
// The mesh blob of dashboard/payloads.py: "FRG1", V, F, K (uint32), neutral (V,3) f32, faces
// (F,3) u32, deltas (K,V,3) f32, little-endian. Views into `buf`, no copy (unless misaligned).
const GEOMETRY_MAGIC = 0x31475246; // "FRG1" read as a little-endian uint32
function decodeGeometry(buf, byteOffset = 0, byteLength = buf.byteLength - byteOffset) {
  if (byteOffset % 4) {
    buf = buf.slice(byteOffset, byteOffset + byteLength);
    byteOffset = 0;
  }
  if (byteLength < 16) throw new Error(`mesh payload of ${byteLength} bytes`);
  const head = new Uint32Array(buf, byteOffset, 4);
  if (head[0] !== GEOMETRY_MAGIC) throw new Error("not a face-retarget mesh payload");
  const V = head[1], F = head[2], K = head[3];
  const need = 16 + 12 * V + 12 * F + 12 * K * V;
  if (byteLength !== need) throw new Error(`mesh payload of ${byteLength} bytes, expected ${need}`);
  let o = byteOffset + 16;
  const neutral = new Float32Array(buf, o, 3 * V); o += 12 * V;
  const faces = new Uint32Array(buf, o, 3 * F); o += 12 * F;
  const deltas = new Float32Array(buf, o, 3 * V * K);
  return { V, F, K, neutral, faces, deltas, bytes: byteLength };
}

// A blob of dashboard/payloads.py from its URL (relative to the page), with the page's cookies
// (the route asks for the same login as the page); the browser's cache keeps it (immutable).
async function fetchBlob(url) {
  const r = await fetch(new URL(url, document.baseURI), { credentials: "same-origin" });
  if (!r.ok) throw new Error(`HTTP ${r.status} ${r.statusText}`);
  return r.arrayBuffer();
}

// The track blob of dashboard/payloads.py: "FRT1", T, K, 0 (uint32), then (T,K) f32 rows.
const TRACK_MAGIC = 0x31545246; // "FRT1" read as a little-endian uint32
function decodeTrack(buf) {
  if (buf.byteLength < 16) throw new Error(`track payload of ${buf.byteLength} bytes`);
  const head = new Uint32Array(buf, 0, 4);
  if (head[0] !== TRACK_MAGIC) throw new Error("not a face-retarget track payload");
  const T = head[1], K = head[2];
  if (buf.byteLength !== 16 + 4 * T * K) throw new Error(`track payload of ${buf.byteLength} bytes, expected ${16 + 4 * T * K}`);
  return { T, K, data: new Float32Array(buf, 16, T * K) };
}

function rows(a) {
  // (n, ...) ndarray -> n, or 0 for null / empty
  if (a == null || !a.length) return 0;
  return a.shape ? a.shape[0] : 0;
}

// requestIdleCallback where the browser has it (with a deadline, so that a busy page still
// gets there), else a timeout with a fixed budget.
function whenIdle(fn) {
  if (window.requestIdleCallback) return { idle: window.requestIdleCallback(fn, { timeout: 2000 }) };
  return { timer: setTimeout(() => fn({ timeRemaining: () => 8, didTimeout: false }), 50) };
}
function cancelIdle(h) {
  if (h.idle !== undefined) window.cancelIdleCallback(h.idle); else clearTimeout(h.timer);
}

// Vertices sharing a neutral position (UV seams) get one id, so normals do not crease there.
function weldIds(pos, V) {
  const ids = new Uint32Array(V);
  const seen = new Map();
  for (let i = 0; i < V; i++) {
    const key = `${pos[3 * i]},${pos[3 * i + 1]},${pos[3 * i + 2]}`;
    const j = seen.get(key);
    if (j === undefined) { seen.set(key, i); ids[i] = i; } else ids[i] = j;
  }
  return ids;
}

// Area-weighted vertex normals of positions `p` (+ `d` scaled by 1 when given), welded.
function vertexNormals(p, d, faces, weld, out, acc) {
  acc.fill(0);
  const F = faces.length / 3;
  for (let f = 0; f < F; f++) {
    const a = 3 * faces[3 * f], b = 3 * faces[3 * f + 1], c = 3 * faces[3 * f + 2];
    let ax = p[a], ay = p[a + 1], az = p[a + 2];
    let bx = p[b], by = p[b + 1], bz = p[b + 2];
    let cx = p[c], cy = p[c + 1], cz = p[c + 2];
    if (d) {
      ax += d[a]; ay += d[a + 1]; az += d[a + 2];
      bx += d[b]; by += d[b + 1]; bz += d[b + 2];
      cx += d[c]; cy += d[c + 1]; cz += d[c + 2];
    }
    const ux = bx - ax, uy = by - ay, uz = bz - az;
    const vx = cx - ax, vy = cy - ay, vz = cz - az;
    const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
    for (const v of [a, b, c]) {
      const w = 3 * weld[v / 3];
      acc[w] += nx; acc[w + 1] += ny; acc[w + 2] += nz;
    }
  }
  const V = out.length / 3;
  for (let i = 0; i < V; i++) {
    const w = 3 * weld[i];
    const x = acc[w], y = acc[w + 1], z = acc[w + 2];
    const l = Math.hypot(x, y, z) || 1;
    out[3 * i] = x / l; out[3 * i + 1] = y / l; out[3 * i + 2] = z / l;
  }
  return out;
}


// Vertex-lit ("fast") shading: hemisphere + key + fill Lambert terms evaluated per vertex,
// with three's own morph chunks so it works with GPU morph targets too. Per-pixel PBR
// (MeshStandardMaterial) costs 2-3x more per frame under software WebGL.
const FAST_VERTEX = `
#include <common>
#include <color_pars_vertex>
#include <morphtarget_pars_vertex>
uniform vec3 uAlbedo;
uniform vec3 uSky;
uniform vec3 uGround;
uniform vec3 uKeyDir;
uniform vec3 uKey;
uniform vec3 uFillDir;
uniform vec3 uFill;
varying vec3 vLit;
void main() {
  #include <color_vertex>
  #include <morphinstance_vertex>
  #include <morphcolor_vertex>
  #include <beginnormal_vertex>
  #include <morphnormal_vertex>
  #include <begin_vertex>
  #include <morphtarget_vertex>
  vec3 nView = normalize(normalMatrix * objectNormal);
  vec3 nWorld = normalize(mat3(modelMatrix) * objectNormal);
  vec3 albedo = uAlbedo;
  #ifdef USE_COLOR
    albedo *= vColor.rgb;
  #endif
  vec3 irradiance = mix(uGround, uSky, 0.5 * nWorld.y + 0.5)
                  + uKey * max(dot(nView, uKeyDir), 0.0) + uFill * max(dot(nView, uFillDir), 0.0);
  vLit = albedo * irradiance * RECIPROCAL_PI;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(transformed, 1.0);
}`;
const FAST_FRAGMENT = `
varying vec3 vLit;
void main() {
  gl_FragColor = vec4(vLit, 1.0);
  #include <tonemapping_fragment>
  #include <colorspace_fragment>
}`;

const LIGHTS = { sky: 1.4, ground: 0x444444, key: 2.2, keyDir: [-0.6, 0.8, 1.0], fill: 0.6, fillDir: [0.8, -0.2, 0.6] };

function rendererName(renderer) {
  const gl = renderer.getContext();
  const ext = gl.getExtension("WEBGL_debug_renderer_info");
  return String(ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER));
}

// ---------------------------------------------------------------------------------------
class Viewer {
  constructor(THREE, model, el, view) {
    this.THREE = THREE;
    this.model = model;
    this.el = el;
    this.view = view;
    this.disposed = false;
    this.label = model.label || `viewer-${Object.keys(REGISTRY.viewers).length}`;
    this.lastSync = 0;
    this.lastShown = -1;
    this.pendingRender = null;
    this.override = null; // probe weights (diagnostics), not synced
    this.offsets = null;  // (3V) per-vertex displacement added after the blend, or null
    this.stats = { renders: 0, renderMs: 0, framesShown: 0, framesSkipped: 0, t0: performance.now(),
                   geometryBuilds: 0, offsetUpdates: 0 };
    STATS.viewers[this.label] = this.stats;
    this.pickCount = 0;
    this.geo = null;        // the decoded mesh blob (decodeGeometry), or null
    this.geometryGen = 0;   // the latest mesh load; an older one that finishes later is dropped
    this.trackData = null;  // the track as loaded (loadTrack): {T, K, data} or null
    this.trackGen = 0;      // the latest track load (as geometryGen)
    this.buildDom();
    this.buildScene();
    this.ready = this.start();
  }

  // Everything after the mesh has arrived (fetched when it comes by URL); the viewer appears in
  // window.__faceRetarget.viewers only then.
  async start() {
    await Promise.all([this.loadGeometry(), this.loadTrack()]);
    if (this.disposed) return;
    this.setGeometry();
    this.setNormalMap();
    this.setMarkers();
    this.setHighlight();
    this.clock = clockFor(this.model.sync_group);
    this.clock.join(this);
    this.clock.setZoom(this.clock.camera.zoom);  // a mesh that joins (a new take) keeps every camera outside its mesh
    if (this.clock.members.size === 1) {
      this.clock.fps = this.model.fps;
      this.clock.loop = this.model.loop;
      this.clock.frame = this.clock.clamp(this.model.frame);
    }
    this.watch();
    this.showFrame(this.clock.frame, false);
    if (this.model.playing) this.clock.play(true);
    REGISTRY.viewers[this.label] = this.api();
    // a new mesh or track sent while the first one was loading (before watch() listened)
    if (this.loadedFrom !== (this.model.geometry_url || this.model.geometry)) this.reloadGeometry();
    if (this.trackFrom !== (this.model.track_url || this.model.track)) this.reloadTrack();
  }

  // -- DOM, renderer, camera -----------------------------------------------------------
  buildDom() {
    const THREE = this.THREE;
    this.root = document.createElement("div");
    this.root.style.cssText = "position:relative;width:100%;height:100%;overflow:hidden;";
    this.canvas = document.createElement("canvas");
    this.canvas.className = "face-retarget-canvas";
    this.canvas.dataset.label = this.label;
    this.canvas.style.cssText = "display:block;width:100%;height:100%;touch-action:none;outline:none;";
    this.canvas.tabIndex = 0;
    if (this.model.pick_mode === "vertex") this.canvas.style.cursor = "crosshair";
    this.overlay = document.createElement("div");
    this.overlay.className = "face-retarget-overlay";
    this.overlay.style.cssText =
      "position:absolute;left:8px;top:6px;font:12px sans-serif;color:#ddd;pointer-events:none;" +
      "text-shadow:0 0 3px #000;";
    this.hint = document.createElement("div");
    this.hint.className = "face-retarget-hint";
    this.hint.textContent = "drag: turn · wheel: zoom · double-click resets the view";
    this.hint.style.cssText =
      "position:absolute;right:8px;bottom:6px;font:11px sans-serif;color:#bbb;pointer-events:none;" +
      "text-shadow:0 0 3px #000;";
    // tracking loss: a banner across the view and a yellow frame around it (the label's words
    // alone, 12 px in a corner, were missed: the filled-in frames look like a neutral face)
    this.gapMark = document.createElement("div");
    this.gapMark.className = "face-retarget-gap";
    this.gapMark.style.cssText =
      "position:absolute;inset:0;display:none;pointer-events:none;box-shadow:inset 0 0 0 4px #ffd54f;";
    this.gapBanner = document.createElement("div");
    this.gapBanner.style.cssText =
      "position:absolute;left:50%;top:28px;transform:translateX(-50%);padding:4px 10px;border-radius:4px;" +
      "background:#ffd54f;color:#222;font:bold 13px sans-serif;white-space:nowrap;";
    this.gapMark.append(this.gapBanner);
    this.root.append(this.canvas, this.overlay, this.hint, this.gapMark);
    this.el.replaceChildren(this.root);
    this.renderer = new THREE.WebGLRenderer({ canvas: this.canvas, antialias: false, alpha: false,
                                              powerPreference: "high-performance" });
    this.pixelRatio = Math.min(window.devicePixelRatio || 1, 2);
    this.renderer.setPixelRatio(this.pixelRatio);
    this.scaleStep = 0;  // RENDER_SCALES[scaleStep]: streamed drawing's resolution
    this.scaleWin = null; // the current window of streamed draws {t0, draws, messages, good}
    this.resizeObserver = new ResizeObserver(() => this.resize());
    this.resizeObserver.observe(this.root);
    this.visible = true;
    this.streamHidden = false;
    this.hiddenFrame = false;
    this.intersection = new IntersectionObserver((es) => this.setVisible(es[es.length - 1].isIntersecting));
    this.intersection.observe(this.root);
    this.bindControls();
  }

  buildScene() {
    const THREE = this.THREE;
    const m = this.model;
    this.rendererName = rendererName(this.renderer);
    this.software = /swiftshader|llvmpipe|softpipe|software/i.test(this.rendererName);
    this.blend = m.blend === "auto" ? (this.software ? "cpu" : "gpu") : m.blend;
    this.shading = m.shading === "auto" ? (this.software ? "fast" : "standard") : m.shading;
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(m.background_color);
    this.camera = new THREE.PerspectiveCamera(25, 1, 0.001, 100);
    this.scene.add(this.camera);
    this.scene.add(new THREE.HemisphereLight(0xffffff, LIGHTS.ground, LIGHTS.sky));
    // key light rides with the camera (upper left of the view), so orbiting keeps the face lit
    for (const [intensity, dir] of [[LIGHTS.key, LIGHTS.keyDir], [LIGHTS.fill, LIGHTS.fillDir]]) {
      const light = new THREE.DirectionalLight(0xffffff, intensity);
      light.position.set(...dir);
      this.camera.add(light);
      this.camera.add(light.target);
      light.target.position.set(0, 0, 0);
    }
    this.normalTexture = null;
    this.material = this.makeMaterial(this.materialKind());
    this.markerMaterial = new THREE.MeshBasicMaterial({ color: m.marker_color });
    this.highlightMaterial = new THREE.MeshBasicMaterial({ color: m.highlight_color });
    // drag preview: a line from the start point to the pointer, drawn over the mesh
    this.dragMaterial = new THREE.LineBasicMaterial({ color: m.highlight_color, depthTest: false, transparent: true });
    const lg = new THREE.BufferGeometry();
    lg.setAttribute("position", new THREE.BufferAttribute(new Float32Array(6), 3));
    this.dragLine = new THREE.Line(lg, this.dragMaterial);
    this.dragLine.frustumCulled = false;
    this.dragLine.renderOrder = 10;
    this.dragLine.visible = false;
    this.dragEnd = new THREE.Mesh(new THREE.SphereGeometry(1, 12, 10), this.highlightMaterial);
    this.dragEnd.frustumCulled = false;
    this.dragEnd.visible = false;
    this.scene.add(this.dragLine, this.dragEnd);
  }

  // "fast" (per-vertex Lambert) unless shading is "standard" or a normal map is shown: the
  // per-vertex shader has no per-pixel normal to read a map into.
  materialKind() {
    return this.shading === "standard" || (this.normalTexture && this.hasUvs) ? "standard" : "fast";
  }

  makeMaterial(kind) {
    const THREE = this.THREE;
    const m = this.model;
    let material;
    if (kind === "fast") {
      const ground = new THREE.Color(LIGHTS.ground).multiplyScalar(LIGHTS.sky);
      material = new THREE.ShaderMaterial({
        vertexShader: FAST_VERTEX,
        fragmentShader: FAST_FRAGMENT,
        // back faces culled: ~25% less work under SwiftShader; a look into the open neck
        // from below shows through (the standard shading draws both sides)
        side: THREE.FrontSide,
        uniforms: {
          uAlbedo: { value: new THREE.Color(m.mesh_color) },
          uSky: { value: new THREE.Color(0xffffff).multiplyScalar(LIGHTS.sky) },
          uGround: { value: ground },
          uKeyDir: { value: new THREE.Vector3(...LIGHTS.keyDir).normalize() },
          uKey: { value: new THREE.Color(0xffffff).multiplyScalar(LIGHTS.key) },
          uFillDir: { value: new THREE.Vector3(...LIGHTS.fillDir).normalize() },
          uFill: { value: new THREE.Color(0xffffff).multiplyScalar(LIGHTS.fill) },
        },
      });
      material.color = material.uniforms.uAlbedo.value; // same API as the standard one
    } else {
      material = new THREE.MeshStandardMaterial({ color: m.mesh_color, roughness: 0.65,
                                                  metalness: 0.0, side: THREE.DoubleSide });
    }
    material.userData.kind = kind;
    return material;
  }

  // Swap the material when its kind changes (normal map on/off under "fast" shading), then
  // attach or detach the normal map.
  updateMaterial() {
    const THREE = this.THREE;
    const kind = this.materialKind();
    if (this.material.userData.kind !== kind) {
      const old = this.material;
      this.material = this.makeMaterial(kind);
      if (this.mesh) this.mesh.material = this.material;
      old.dispose();
      this.setColors();
    }
    if (kind !== "standard") return;
    const tex = this.normalTexture && this.hasUvs ? this.normalTexture : null;
    const type = this.model.normal_map_space === "tangent" ? THREE.TangentSpaceNormalMap : THREE.ObjectSpaceNormalMap;
    if (this.material.normalMap !== tex || this.material.normalMapType !== type) {
      this.material.normalMap = tex;
      this.material.normalMapType = type;
      this.material.needsUpdate = true;
    }
  }

  // uvs (V, 2) as the geometry's "uv" attribute (the normal map's channel 0)
  setUvs(geom) {
    const THREE = this.THREE;
    geom = geom || (this.mesh && this.mesh.geometry);
    if (!geom) return;
    const uv = this.model.uvs;
    this.hasUvs = uv != null && rows(uv) === this.V && this.V > 0;
    if (this.hasUvs) geom.setAttribute("uv", new THREE.BufferAttribute(asF32(uv), 2));
    else if (geom.getAttribute("uv")) geom.deleteAttribute("uv");
  }

  // normal_map (H, W, 3) uint8 -> an RGBA DataTexture (WebGL2 has no RGB8 upload in three r187).
  // Row 0 of the array is v = 0 (flipY false): glTF's top-left UV origin, core.normalmap's layout.
  // A map of the same size reuses its texture (re-uploaded on change, no new GL object).
  setNormalMap() {
    const THREE = this.THREE;
    const nm = this.model.normal_map;
    const t = performance.now();
    if (nm == null || !rows(nm) || !nm.shape || nm.shape.length !== 3 || nm.shape[2] !== 3) {
      if (this.normalTexture) this.normalTexture.dispose();
      this.normalTexture = null;
    } else {
      const H = nm.shape[0], W = nm.shape[1], n = W * H;
      let tex = this.normalTexture;
      if (!tex || tex.image.width !== W || tex.image.height !== H) {
        if (tex) tex.dispose();
        tex = new THREE.DataTexture(new Uint8Array(4 * n), W, H, THREE.RGBAFormat, THREE.UnsignedByteType);
        tex.flipY = false;
        tex.colorSpace = THREE.NoColorSpace; // vectors, not colours: no sRGB decode
        tex.magFilter = THREE.LinearFilter;
        tex.minFilter = THREE.LinearMipmapLinearFilter;
        tex.generateMipmaps = true;
        tex.wrapS = tex.wrapT = THREE.ClampToEdgeWrapping;
        this.normalTexture = tex;
      }
      const out = tex.image.data;
      for (let i = 0, j = 0; i < n; i++, j += 3) {
        out[4 * i] = nm[j]; out[4 * i + 1] = nm[j + 1]; out[4 * i + 2] = nm[j + 2]; out[4 * i + 3] = 255;
      }
      tex.needsUpdate = true;
      this.stats.normalMapUpdates = (this.stats.normalMapUpdates || 0) + 1;
    }
    this.stats.normalMapMs = performance.now() - t;
    this.updateMaterial();
  }

  // The mesh from `geometry_url` (fetched with the page's cookies; the browser's cache keeps it,
  // the URL being its content's hash) or from the inline `geometry` blob, into this.geo.
  // Resolves true when this load is the latest (the caller then rebuilds), false otherwise.
  async loadGeometry() {
    const gen = ++this.geometryGen;
    const m = this.model;
    this.loadedFrom = m.geometry_url || m.geometry;
    const t = performance.now();
    let geo = null, error = null;
    try {
      if (m.geometry_url) {
        geo = decodeGeometry(await fetchBlob(m.geometry_url));
      } else if (m.geometry && m.geometry.length) {
        const b = m.geometry;
        geo = decodeGeometry(b.buffer, b.byteOffset, b.byteLength);
      }
    } catch (err) {
      error = String(err && err.message || err);
    }
    if (gen !== this.geometryGen || this.disposed) return false;
    this.geo = geo;
    this.stats.geometryMs = performance.now() - t;
    this.stats.geometryBytes = geo ? geo.bytes : 0;
    this.stats.geometrySource = m.geometry_url ? "url" : (geo ? "inline" : "none");
    this.stats.geometryError = error;
    if (error) console.error(`face-retarget viewer ${this.label}: the mesh could not be loaded (${error})`);
    return true;
  }

  // The track from `track_url` (fetched like the mesh; a new track is a new URL) or the inline
  // `track`, into this.trackData. Resolves true when this load is the latest.
  async loadTrack() {
    const gen = ++this.trackGen;
    const m = this.model;
    this.trackFrom = m.track_url || m.track;
    let data = null, error = null;
    try {
      if (m.track_url) {
        data = decodeTrack(await fetchBlob(m.track_url));
      } else if (rows(m.track)) {
        data = { T: rows(m.track), K: m.track.shape[1], data: asF32(m.track) };
      }
    } catch (err) {
      error = String(err && err.message || err);
    }
    if (gen !== this.trackGen || this.disposed) return false;
    this.trackData = data;
    this.stats.trackSource = m.track_url ? "url" : (data ? "inline" : "none");
    this.stats.trackError = error;
    if (error) console.error(`face-retarget viewer ${this.label}: the weight track could not be loaded (${error})`);
    return true;
  }

  async reloadTrack() {
    if (!(await this.loadTrack())) return;
    this.setTrack(); this.showFrame(this.clock.clamp(this.clock.frame), false);
  }

  async reloadGeometry() {
    if (!(await this.loadGeometry())) return;
    this.setGeometry(); this.setMarkers(); this.setHighlight(); this.showFrame(this.clock.clamp(this.clock.frame), false);
  }

  setGeometry() {
    const THREE = this.THREE;
    const m = this.model;
    if (this.mesh) {
      this.scene.remove(this.mesh);
      this.disposeGeometry();
      this.mesh = null;
    }
    this.gpu = null; this.dynamic = null; this.morphing = false; this.offsets = null;
    const g = this.geo;
    const V = g ? g.V : 0;
    this.V = V;
    this.K = V ? g.K : 0;
    if (!V) { this.nFrames = 1; this.hasUvs = false; return; }
    const pos = g.neutral;
    const faces = g.faces;
    const geom = new THREE.BufferGeometry();
    geom.setAttribute("position", new THREE.BufferAttribute(pos, 3));
    geom.setIndex(new THREE.BufferAttribute(faces, 1));
    const t = performance.now();
    const weld = weldIds(pos, V);
    const acc = new Float32Array(3 * V);
    this.faces = faces; this.weld = weld; this.acc = acc; // reused for the normals of offset meshes
    this.stats.geometryBuilds += 1;
    const n0 = vertexNormals(pos, null, faces, weld, new Float32Array(3 * V), acc);
    geom.setAttribute("normal", new THREE.BufferAttribute(n0, 3));
    const deltas = this.K ? g.deltas : new Float32Array(0);
    this.deltas = deltas;
    this.neutral = pos;
    this.normal0 = n0;
    const mp = [], mn = [];
    // per-shape normal deltas: all of them now for the GPU's morph targets; for the JS blend
    // only when a shape is first blended (normalDelta), the rest while the page is idle — the
    // first frame is drawn without waiting for every shape of a large rig (issue 30)
    this.normalDeltas = new Array(this.K).fill(null);
    this.normalExtent = new Float32Array(this.K); // per shape, max |dn_k| (set by normalDelta)
    this.blendedW = null;   // the weights the JS blend's buffers hold (null: re-blend from scratch)
    this.sinceFull = 0;
    this.nk = new Float32Array(3 * V);
    if (this.idleNormals) { cancelIdle(this.idleNormals); this.idleNormals = null; }
    const eager = this.K && this.blend === "gpu";
    for (let k = 0; k < this.K; k++) {
      const dk = deltas.subarray(k * 3 * V, (k + 1) * 3 * V);
      mp.push(new THREE.BufferAttribute(dk, 3));
      if (eager) mn.push(new THREE.BufferAttribute(this.normalDelta(k), 3));
    }
    this.stats.normalsMs = performance.now() - t;
    if (!eager && this.K) this.fillNormalsWhenIdle();
    // per shape, the largest |delta| per axis: bounds the morphed mesh for ray tests
    this.deltaExtent = new Float32Array(3 * this.K);
    for (let k = 0; k < this.K; k++) {
      const o = k * 3 * V;
      for (let i = 0; i < 3 * V; i++) {
        const a = Math.abs(deltas[o + i]);
        if (a > this.deltaExtent[3 * k + (i % 3)]) this.deltaExtent[3 * k + (i % 3)] = a;
      }
    }
    this.current = new Float32Array(this.K);
    this.blended = null;
    if (this.K && this.blend === "gpu") {
      geom.morphAttributes.position = mp;
      geom.morphAttributes.normal = mn;
      geom.morphTargetsRelative = true;
      // kept to swap back in after the JS blend stood in for them (offsets set)
      this.gpu = { base: { position: geom.getAttribute("position"), normal: geom.getAttribute("normal") },
                   morph: { position: mp, normal: mn } };
      this.morphing = true;
    } else {
      // cpu: own copies the blend writes into every frame
      const d = this.jsBuffers();
      geom.setAttribute("position", d.position);
      geom.setAttribute("normal", d.normal);
    }
    this.setColors(geom);
    this.setUvs(geom);
    // frame the neutral: three's computeBoundingBox also adds every morph target's delta box
    geom.boundingBox = new THREE.Box3().setFromBufferAttribute(geom.getAttribute("position"));
    geom.boundingSphere = geom.boundingBox.getBoundingSphere(new THREE.Sphere());
    this.mesh = new THREE.Mesh(geom, this.material);
    this.mesh.frustumCulled = false; // the bounding box is the neutral's; morphs move outside it
    if (this.gpu) this.mesh.updateMorphTargets();
    this.scene.add(this.mesh);
    this.updateMaterial();
    this.bbox = geom.boundingBox.clone();
    this.size = this.bbox.min.distanceTo(this.bbox.max);
    this.setTrack();
    this.setOffsets();
    this.fitCamera();
  }

  // Shape k's normal delta (vertex normals of neutral + delta_k, minus the neutral's), made
  // on first use and kept.
  normalDelta(k) {
    let dn = this.normalDeltas[k];
    if (dn) return dn;
    const t = performance.now();
    const V = this.V, n0 = this.normal0, nk = this.nk;
    vertexNormals(this.neutral, this.deltas.subarray(k * 3 * V, (k + 1) * 3 * V), this.faces, this.weld, nk, this.acc);
    dn = new Float32Array(3 * V);
    let ext = 0;
    for (let i = 0; i < 3 * V; i++) { dn[i] = nk[i] - n0[i]; if (Math.abs(dn[i]) > ext) ext = Math.abs(dn[i]); }
    this.normalExtent[k] = ext;
    this.normalDeltas[k] = dn;
    this.stats.normalsMs += performance.now() - t;
    return dn;
  }

  // The normal deltas not made yet, a few shapes at a time while the page is idle (so that
  // playback later does not pay for them frame by frame).
  fillNormalsWhenIdle() {
    const step = (deadline) => {
      this.idleNormals = null;
      if (this.disposed || !this.normalDeltas) return;
      let k = this.normalDeltas.indexOf(null);
      while (k >= 0 && (deadline.timeRemaining() > 2 || deadline.didTimeout)) {
        this.normalDelta(k);
        k = this.normalDeltas.indexOf(null, k + 1);
        if (deadline.didTimeout) break;
      }
      if (k >= 0) this.idleNormals = whenIdle(step);
    };
    this.idleNormals = whenIdle(step);
  }

  // The JS blend's dynamic position/normal buffers (created once per geometry).
  jsBuffers() {
    if (!this.dynamic) {
      const THREE = this.THREE;
      const pa = new THREE.BufferAttribute(new Float32Array(this.neutral), 3);
      const na = new THREE.BufferAttribute(new Float32Array(this.normal0), 3);
      pa.setUsage(THREE.DynamicDrawUsage);
      na.setUsage(THREE.DynamicDrawUsage);
      this.dynamic = { position: pa, normal: na };
    }
    return this.dynamic;
  }

  // gpu blend only: put the morph targets (and the static neutral) into the geometry, or the
  // JS blend's buffers in their place. Both sets stay alive, so switching rebuilds nothing
  // (three keeps its morph texture per geometry and recompiles nothing it has seen before).
  useMorphTargets(on) {
    const g = this.gpu;
    this.morphing = Boolean(g && on);
    if (!g) return;
    const geom = this.mesh.geometry;
    const want = on ? g.base : this.jsBuffers();
    if (geom.getAttribute("position") === want.position) return;
    geom.setAttribute("position", want.position);
    geom.setAttribute("normal", want.normal);
    if (on) {
      geom.morphAttributes.position = g.morph.position;
      geom.morphAttributes.normal = g.morph.normal;
    } else {
      delete geom.morphAttributes.position;
      delete geom.morphAttributes.normal;
    }
  }

  // offsets (V, 3) f32 -> this.offsets (or null when unset or of another V). The next
  // applyFrame re-blends: with offsets in JS (exact normals), without them as before.
  setOffsets() {
    const o = this.model.offsets;
    this.offsets = o != null && this.V > 0 && rows(o) === this.V && o.length === 3 * this.V ? asF32(o) : null;
    if (this.mesh) this.useMorphTargets(this.offsets === null);
    this.blended = null;
    this.blendedW = null;
    this.stats.offsetUpdates += 1;
  }

  // Dispose the mesh's geometry with the attribute set swapped out of it (gpu blend).
  disposeGeometry() {
    const geom = this.mesh.geometry;
    if (this.gpu && this.dynamic) {
      const spare = geom.getAttribute("position") === this.dynamic.position ? this.gpu.base : this.dynamic;
      geom.setAttribute("sparePosition", spare.position); // only so that dispose() frees their GL buffers
      geom.setAttribute("spareNormal", spare.normal);
    }
    geom.dispose();
  }

  setColors(geom) {
    const THREE = this.THREE;
    geom = geom || (this.mesh && this.mesh.geometry);
    if (!geom) return;
    const c = this.model.colors;
    if (c != null && rows(c) === this.V) {
      geom.setAttribute("color", new THREE.BufferAttribute(asF32(c), 3));
      this.material.vertexColors = true;
      this.material.color.set(0xffffff);  // the map is the albedo
    } else {
      if (geom.getAttribute("color")) geom.deleteAttribute("color");
      this.material.vertexColors = false;
      this.material.color.set(this.model.mesh_color);
    }
    this.material.needsUpdate = true;
  }

  setTrack() {
    const tr = this.trackData;
    if (tr && tr.T && tr.K === this.K) {
      this.track = tr.data;
      this.trackRows = tr.T;
      this.nFrames = tr.T;
    } else {
      this.track = null;
      this.trackRows = 0;
      this.nFrames = 1;
    }
    const mt = this.model.marker_track;
    this.nFrames = Math.max(this.nFrames, rows(mt));
  }

  setMarkers() {
    const THREE = this.THREE;
    const m = this.model;
    if (this.markers) {
      this.scene.remove(this.markers);
      this.markers.geometry.dispose();
      this.markers = null;
    }
    const lv = m.marker_vertices, lw = m.marker_weights, mt = m.marker_track;
    this.layoutV = null; this.markerTrack = null;
    let M = 0;
    if (rows(mt)) {
      this.markerTrack = asF32(mt);
      M = mt.shape[1];
    } else if (rows(lv) && rows(lw) === rows(lv)) {
      this.layoutV = asU32(lv);
      this.layoutW = asF32(lw);
      M = rows(lv);
    }
    this.M = M;
    if (!M || !this.V) return;
    const r = m.marker_radius * (this.size || 1);
    // drawn flat (MeshBasicMaterial): only the outline shows, and an icosphere of 80 triangles
    // outlines as round as a 10 x 8 UV sphere of 140; SwiftShader's time is about linear in
    // triangles, and the markers were a quarter of a live view's draw (docs/live.md)
    const sphere = new THREE.IcosahedronGeometry(r, 1);
    this.markers = new THREE.InstancedMesh(sphere, this.markerMaterial, M);
    this.markers.frustumCulled = false;
    this.markers.visible = m.show_markers;
    this.markerPos = new Float32Array(3 * M);
    this.scene.add(this.markers);
    this.nFrames = Math.max(this.nFrames || 1, rows(mt));
  }

  updateMarkers(w, frame) {
    if (!this.markers) return;
    const M = this.M, V = this.V, K = this.K, P = this.markerPos;
    if (this.markerTrack) {
      const T = this.model.marker_track.shape[0];
      const f = Math.min(frame, T - 1);
      P.set(this.markerTrack.subarray(3 * M * f, 3 * M * (f + 1)));
    } else {
      const N = this.neutral, D = this.deltas, LV = this.layoutV, LW = this.layoutW, O = this.offsets;
      for (let i = 0; i < M; i++) {
        let x = 0, y = 0, z = 0;
        for (let j = 0; j < 3; j++) {
          const b = LW[3 * i + j];
          if (b === 0) continue;
          const v = 3 * LV[3 * i + j];
          let px = N[v], py = N[v + 1], pz = N[v + 2];
          if (O) { px += O[v]; py += O[v + 1]; pz += O[v + 2]; }
          for (let k = 0; k < K; k++) {
            const wk = w[k];
            if (wk === 0) continue;
            const o = k * 3 * V + v;
            px += wk * D[o]; py += wk * D[o + 1]; pz += wk * D[o + 2];
          }
          x += b * px; y += b * py; z += b * pz;
        }
        P[3 * i] = x; P[3 * i + 1] = y; P[3 * i + 2] = z;
      }
    }
    const THREE = this.THREE;
    const mat = this._mat || (this._mat = new THREE.Matrix4());
    for (let i = 0; i < M; i++) {
      mat.makeTranslation(P[3 * i], P[3 * i + 1], P[3 * i + 2]);
      this.markers.setMatrixAt(i, mat);
    }
    this.markers.instanceMatrix.needsUpdate = true;
  }

  // -- highlighted vertices -----------------------------------------------------------------
  setHighlight() {
    const THREE = this.THREE;
    if (this.highlights) {
      this.scene.remove(this.highlights);
      this.highlights.geometry.dispose();
      this.highlights = null;
    }
    const ids = (this.model.highlight || []).filter((v) => Number.isInteger(v) && v >= 0 && v < this.V);
    this.highlightIds = ids;
    if (!ids.length) return;
    const r = this.model.highlight_radius * (this.size || 1);
    this.highlights = new THREE.InstancedMesh(new THREE.SphereGeometry(r, 12, 10), this.highlightMaterial, ids.length);
    this.highlights.frustumCulled = false;
    this.highlights.renderOrder = 5;
    this.scene.add(this.highlights);
    this.updateHighlight();
  }

  updateHighlight() {
    if (!this.highlights) return;
    const mat = this._hmat || (this._hmat = new this.THREE.Matrix4());
    const p = this._hvec || (this._hvec = new this.THREE.Vector3());
    this.highlightIds.forEach((v, i) => {
      this.vertexPosition(v, p);
      mat.makeTranslation(p.x, p.y, p.z);
      this.highlights.setMatrixAt(i, mat);
    });
    this.highlights.instanceMatrix.needsUpdate = true;
  }

  // -- picking -------------------------------------------------------------------------------
  // Vertex v as shown now: neutral + sum_k w_k delta_k (+ offset) with the weights of the
  // shown frame (the JS blend wrote this into the position buffer, up to float32 rounding; for
  // streamed weights within the bound of its deferred changes, DEFER_TOL x size; on the gpu it
  // never leaves the shader, so it is recomputed here from the same weights).
  vertexPosition(v, out) {
    const N = this.neutral, D = this.deltas, w = this.current, V = this.V, O = this.offsets;
    let x = N[3 * v], y = N[3 * v + 1], z = N[3 * v + 2];
    for (let k = 0; k < this.K; k++) {
      const wk = w[k];
      if (wk === 0) continue;
      const o = k * 3 * V + 3 * v;
      x += wk * D[o]; y += wk * D[o + 1]; z += wk * D[o + 2];
    }
    if (O) { x += O[3 * v]; y += O[3 * v + 1]; z += O[3 * v + 2]; }
    return out.set(x, y, z);
  }

  // Bounds of the shown mesh for the raycaster's early-outs (the geometry's own are the
  // neutral's): exact when blended in JS; with morph targets, the neutral box grown by
  // sum_k |w_k| max|delta_k| per axis, which contains every morphed vertex.
  currentBounds() {
    const THREE = this.THREE;
    if (!this.morphing) return new THREE.Box3().setFromBufferAttribute(this.mesh.geometry.getAttribute("position"));
    const grow = [0, 0, 0];
    for (let k = 0; k < this.K; k++) {
      const a = Math.abs(this.current[k]);
      if (a) for (let c = 0; c < 3; c++) grow[c] += a * this.deltaExtent[3 * k + c];
    }
    const g = new THREE.Vector3(...grow);
    return this.bbox.clone().expandByVector(g);
  }

  rayAt(clientX, clientY) {
    const THREE = this.THREE;
    const rect = this.canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(((clientX - rect.left) / rect.width) * 2 - 1, -((clientY - rect.top) / rect.height) * 2 + 1);
    const rc = this.raycaster || (this.raycaster = new THREE.Raycaster());
    this.camera.updateMatrixWorld();
    rc.setFromCamera(ndc, this.camera);
    return rc;
  }

  // The vertex under the pointer: {vertex, position: Vector3, point: Vector3 (the ray hit),
  // face: [a, b, c]} or null when the ray misses the mesh.
  pickAt(clientX, clientY) {
    if (!this.mesh || !this.V) return null;
    const THREE = this.THREE;
    const t = performance.now();
    const rc = this.rayAt(clientX, clientY);
    const geom = this.mesh.geometry;
    const box = geom.boundingBox, sphere = geom.boundingSphere;
    geom.boundingBox = this.currentBounds();
    geom.boundingSphere = geom.boundingBox.getBoundingSphere(new THREE.Sphere());
    let hits;
    try {
      this.mesh.updateMatrixWorld();
      hits = rc.intersectObject(this.mesh, false);
    } finally {
      geom.boundingBox = box; geom.boundingSphere = sphere;
    }
    this.stats.pickMs = performance.now() - t;
    if (!hits.length) return null;
    const h = hits[0];
    let best = null;
    for (const v of [h.face.a, h.face.b, h.face.c]) {
      const p = this.vertexPosition(v, new THREE.Vector3());
      const d = p.distanceToSquared(h.point);
      if (!best || d < best.d) best = { vertex: v, position: p, d };
    }
    return { vertex: best.vertex, position: best.position, point: h.point.clone(), face: [h.face.a, h.face.b, h.face.c] };
  }

  // Where the pointer's ray meets the plane through `p` facing the camera (a drag in the
  // view plane), or null if the ray is parallel to it.
  planePoint(clientX, clientY, p) {
    const THREE = this.THREE;
    const rc = this.rayAt(clientX, clientY);
    const n = this.camera.getWorldDirection(new THREE.Vector3());
    const plane = new THREE.Plane().setFromNormalAndCoplanarPoint(n, p);
    return rc.ray.intersectPlane(plane, new THREE.Vector3());
  }

  showDrag(start, end) {
    const a = this.dragLine.geometry.getAttribute("position");
    if (start && end) {
      a.array.set([start.x, start.y, start.z, end.x, end.y, end.z]);
      a.needsUpdate = true;
      this.dragEnd.position.copy(end);
      this.dragEnd.scale.setScalar(0.7 * this.model.highlight_radius * (this.size || 1));
      this.dragLine.visible = this.dragEnd.visible = true;
    } else {
      this.dragLine.visible = this.dragEnd.visible = false;
    }
    this.requestRender();
  }

  // JS -> Python: a fresh object each time (and a count), so a repeated pick is an event too
  report(name, value) {
    this.pickCount += 1;
    this.model[name] = { ...value, count: this.pickCount };
  }

  // -- weights and frames ----------------------------------------------------------------
  weightsAt(frame) {
    const K = this.K;
    if (this.override) return this.override;
    if (this.streamed) return this.streamed;
    const w = this.model.weights;
    if (w && w.length === K && K) return w;
    if (this.track) {
      const f = Math.min(frame, this.nFrames - 1, this.trackRows - 1);
      return this.track.subarray(f * K, (f + 1) * K);
    }
    return null;
  }

  showFrame(frame, fromPlayback) {
    if (this.disposed) return;
    if (fromPlayback && this.lastShown >= 0) {
      const n = this.clock.nFrames;
      const step = (frame - this.lastShown + n) % n;
      this.stats.framesShown += 1;
      if (step > 1) this.stats.framesSkipped += step - 1;
    }
    this.lastShown = frame;
    // a hidden view (another tab, scrolled away) keeps time with its group and draws nothing
    // until it shows again (setVisible)
    const hidden = fromPlayback && !this.visible;
    this.hiddenFrame = hidden;
    if (!hidden) this.applyFrame(frame);
    if (fromPlayback) {
      if (!hidden) this.renderNow();
      const si = this.model.sync_interval;
      const now = performance.now();
      // while playing only the group's first viewer reports (they all show the same frame)
      const leader = this.clock.members.values().next().value === this;
      if (leader && si > 0 && now - this.lastSync >= si * 1000) this.reportFrame(frame);
    } else {
      this.requestRender();
    }
  }

  applyFrame(frame) {
    const w = this.weightsAt(frame);
    const K = this.K, cur = this.current;
    let same = this.blended !== null;
    for (let k = 0; k < K; k++) {
      const x = w ? w[k] : 0;
      if (cur[k] !== x) { cur[k] = x; same = false; }
    }
    if (this.mesh && !same) {
      if (this.morphing) {
        const infl = this.mesh.morphTargetInfluences;
        for (let k = 0; k < K; k++) infl[k] = cur[k];
      } else {
        this.blendCpu(cur, w === this.streamed);
      }
      this.blended = frame;
    }
    this.updateMarkers(cur, frame);
    this.updateHighlight();
    const T = this.nFrames;
    this.overlay.textContent = `${this.model.label || ""}  frame ${frame} / ${T - 1}` + this.scaleNote() +
      (this.override ? "  (probe)" : (this.model.weights && this.model.weights.length ? "  (weights from Python)" : "")) +
      (!this.override && this.isGap(frame) ? "  — no tracking data at this frame (filled in)" : "") +
      (this.stats.geometryError ? `  — the mesh could not be loaded (${this.stats.geometryError}); reload the page` : "") +
      (this.stats.trackError ? `  — the weight track could not be loaded (${this.stats.trackError}); reload the page` : "");
    this.overlay.style.color = this.stats.geometryError || this.stats.trackError ? "#ff8a80"
      : (!this.override && this.isGap(frame) ? "#ffd54f" : "#ddd");
    const gap = this.override ? null : this.gapOf(frame);
    this.gapMark.style.display = gap ? "block" : "none";
    if (gap) this.gapBanner.textContent = gap[0] === gap[1] ? `No tracking data at frame ${gap[0]} (filled in)`
      : `No tracking data: frames ${gap[0]}–${gap[1]} (filled in)`;
  }

  // The gap ([first, last] frame range without data) `frame` lies in, or null.
  gapOf(frame) {
    for (const g of this.model.gaps || []) if (frame >= g[0] && frame <= g[1]) return g;
    return null;
  }

  // Whether `frame` lies in one of the model's gaps.
  isGap(frame) {
    return this.gapOf(frame) !== null;
  }

  // position = neutral + sum_k w_k delta_k, normal = n0 + sum_k w_k dn_k: streamed weights
  // incrementally (header), anything else from scratch, so that a track frame, a probe or a
  // seek shows the same bits however it was reached. With offsets: position += offset, normal =
  // the area-weighted vertex normal of the final positions (exact: blended normal deltas know
  // nothing of the offsets).
  blendCpu(w, incremental = false) {
    const t = performance.now();
    const geom = this.mesh.geometry;
    const pa = geom.getAttribute("position"), na = geom.getAttribute("normal");
    const P = pa.array, Nn = na.array, K = this.K, st = this.stats;
    const bw = this.blendedW;
    let apply = null;
    if (incremental && bw && !this.offsets && !window.__faceRetargetFullBlend && this.sinceFull < REBLEND_EVERY) {
      apply = this.changedShapes(w, bw);
      let nonzero = 0;
      for (let k = 0; k < K; k++) if (w[k] !== 0) nonzero += 1;
      if (apply.length >= nonzero) apply = null; // from scratch costs no more
    }
    if (apply === null) {
      this.blendDense(w, P, Nn);
      if (this.offsets) this.blendedW = null;
      else (this.blendedW && this.blendedW.length === K ? this.blendedW : (this.blendedW = new Float32Array(K))).set(w);
      this.sinceFull = 0;
      this.deferredBound = 0;
      st.fullBlends = (st.fullBlends || 0) + 1;
    } else {
      for (const k of apply) this.addShape(k, w[k] - bw[k], P, Nn);
      for (const k of apply) bw[k] = w[k];
      this.sinceFull += 1;
      st.incrementalBlends = (st.incrementalBlends || 0) + 1;
      st.blendShapes = (st.blendShapes || 0) + apply.length;
    }
    pa.needsUpdate = true;
    na.needsUpdate = true;
    st.blendMs = (st.blendMs || 0) + performance.now() - t;
  }

  // The shapes to blend for w when the buffers hold bw: those whose change is not deferred.
  // Changes are deferred smallest bound first while the deferred shapes' bounds on the error,
  // sum |w_k - bw_k| max|delta_k| and sum |w_k - bw_k| max|dn_k|, stay within DEFER_TOL x size
  // and DEFER_TOL_NORMAL (the header): what the buffers show then differs from the exact blend
  // of w by at most that in any coordinate.
  changedShapes(w, bw) {
    const changed = [];
    for (let k = 0; k < this.K; k++) if (w[k] !== bw[k]) changed.push(k);
    const ext = this.deltaExtent, next = this.normalExtent;
    const boundP = (k) => Math.abs(w[k] - bw[k]) * Math.max(ext[3 * k], ext[3 * k + 1], ext[3 * k + 2]);
    const boundN = (k) => Math.abs(w[k] - bw[k]) * next[k];
    changed.sort((a, b) => boundP(a) - boundP(b));
    let eP = 0, eN = 0, deferred = 0;
    const tolP = DEFER_TOL * this.size;
    for (const k of changed) {
      this.normalDelta(k); // makes normalExtent[k]
      const p = boundP(k), n = boundN(k);
      if (eP + p > tolP || eN + n > DEFER_TOL_NORMAL) break;
      eP += p; eN += n; deferred += 1;
    }
    this.stats.deferredShapes = (this.stats.deferredShapes || 0) + deferred;
    this.deferredBound = eP / (this.size || 1);
    return changed.slice(deferred);
  }

  // P += c delta_k, Nn += c dn_k (3V each).
  addShape(k, c, P, Nn) {
    const n3 = 3 * this.V, d = this.deltas.subarray(k * n3, (k + 1) * n3), dn = this.normalDelta(k);
    for (let i = 0; i < n3; i++) { P[i] += c * d[i]; Nn[i] += c * dn[i]; }
  }

  // The blend from scratch over the dense deltas into P (3V) and Nn (3V): neutral (+ offsets)
  // + sum over non-zero w_k of w_k delta_k; normals n0 + sum w_k dn_k, or with offsets the
  // vertex normals of the final positions. The reference the incremental blend is tested against.
  blendDense(w, P, Nn) {
    const D = this.deltas, n3 = 3 * this.V, O = this.offsets;
    P.set(this.neutral);
    if (O) {
      for (let k = 0; k < this.K; k++) {
        const wk = w[k];
        if (wk === 0) continue;
        const d = D.subarray(k * n3, (k + 1) * n3);
        for (let i = 0; i < n3; i++) P[i] += wk * d[i];
      }
      for (let i = 0; i < n3; i++) P[i] += O[i];
      const tn = performance.now();
      vertexNormals(P, null, this.faces, this.weld, Nn, this.acc);
      this.stats.offsetNormalsMs = performance.now() - tn;
    } else {
      Nn.set(this.normal0);
      for (let k = 0; k < this.K; k++) if (w[k] !== 0) this.addShape(k, w[k], P, Nn);
    }
  }

  reportFrame(frame) {
    this.lastSync = performance.now();
    if (this.model.frame === frame) return;
    this.clock.remember(frame);
    this.reporting = true;
    try { this.model.frame = frame; } finally { this.reporting = false; }
  }

  playbackStarted() {
    this.lastShown = this.clock.frame;
    this.lastSync = performance.now();
    if (!this.model.playing) { this.reporting = true; try { this.model.playing = true; } finally { this.reporting = false; } }
  }

  playbackStopped(frame) {
    this.reportFrame(frame);
    if (this.model.playing) { this.reporting = true; try { this.model.playing = false; } finally { this.reporting = false; } }
  }

  // Back from streamed weights to the model's weights or track: full resolution again.
  endStream() {
    this.streamed = null;
    this.scaleWin = null;
    this.setScaleStep(0);
  }

  // Streamed weights (K numbers) kept in one buffer per view, drawn at the next animation frame.
  receiveStreamed(weights) {
    const t = performance.now();
    if (!this.streamed || this.streamed.length !== this.K) this.streamed = new Float32Array(this.K);
    this.streamed.set(weights);
    const st = this.stats;
    st.streamed = (st.streamed || 0) + 1;
    st.messageMs = (st.messageMs || 0) + performance.now() - t;
    if (!this.visible) { this.streamHidden = true; return; }
    if (!this.streamPending) this.streamPending = requestAnimationFrame((t) => this.drawStreamed(t));
  }

  // -- rendering ---------------------------------------------------------------------------
  // The latest streamed weights, blended and drawn in this animation frame (one draw).
  drawStreamed(frameTime) {
    this.streamPending = null;
    if (this.disposed) return;
    const t = performance.now();
    if (frameTime !== undefined) requestAnimationFrame((next) => this.frameCost(next - frameTime));
    this.applyFrame(this.clock.frame);
    if (this.pendingRender !== null) { cancelAnimationFrame(this.pendingRender); this.pendingRender = null; }
    this.renderNow();
    // hand the draw to the GPU now, not at the end of the animation frame: SwiftShader draws this
    // view while the next view blends
    this.renderer.getContext().flush();
    const st = this.stats;
    st.streamDraws = (st.streamDraws || 0) + 1;
    const key = `draws@${RENDER_SCALES[this.scaleStep]}`;
    st[key] = (st[key] || 0) + 1;
    st.streamDrawMs = (st.streamDrawMs || 0) + performance.now() - t;
  }

  // A streamed draw's frame cost `ms` into the window; at its end, pick the render scale
  // (nextScaleStep) and start the next window.
  frameCost(ms) {
    if (this.disposed || !this.streamed) return;
    const win = this.scaleWin || (this.scaleWin = { draws: 0, ms: 0, good: 0 });
    win.draws += 1;
    win.ms += ms;
    if (win.draws < SCALE_WINDOW) return;
    this.frameMs = win.ms / win.draws;
    // window.__faceRetargetRenderScale = one of RENDER_SCALES pins it (comparisons in one page)
    const pin = RENDER_SCALES.indexOf(window.__faceRetargetRenderScale);
    const [step, good] = pin >= 0 ? [pin, 0] : nextScaleStep(this.scaleStep, this.frameMs, win.good);
    this.setScaleStep(step);
    this.scaleWin = { draws: 0, ms: 0, good };
  }

  setScaleStep(step) {
    if (step === this.scaleStep) return;
    this.scaleStep = step;
    this.stats.scaleChanges = (this.stats.scaleChanges || 0) + 1;
    this.renderer.setPixelRatio(this.pixelRatio * RENDER_SCALES[step]);
    if (this.width) this.renderer.setSize(this.width, this.height, false);
  }

  // What the overlay says about the streamed drawing's resolution ("" at full resolution).
  scaleNote() {
    if (!this.scaleStep) return "";
    return `  · drawn at ${Math.round(100 * RENDER_SCALES[this.scaleStep])}% resolution to keep up with the stream ` +
      `(its frames took ${Math.round(this.frameMs)} ms)`;
  }

  // Shown on the page or not (a tab not selected, scrolled away): streamed weights and playback
  // skip hidden views, which draw the latest when they show again.
  setVisible(on) {
    if (on === this.visible) return;
    this.visible = on;
    if (on && this.hiddenFrame && !this.disposed && this.clock) {
      this.hiddenFrame = false;
      this.applyFrame(this.clock.frame);
      this.requestRender();
    }
    if (on && this.streamHidden && !this.disposed) {
      this.streamHidden = false;
      if (!this.streamPending) this.streamPending = requestAnimationFrame((t) => this.drawStreamed(t));
    }
  }

  requestRender() {
    if (this.pendingRender !== null || this.disposed) return;
    this.pendingRender = requestAnimationFrame(() => { this.pendingRender = null; this.renderNow(); });
  }

  renderNow() {
    if (this.disposed || !this.width) return;
    const t = performance.now();
    this.renderer.render(this.scene, this.camera);
    this.stats.renderMs += performance.now() - t;
    this.stats.renders += 1;
  }

  resize() {
    const w = Math.max(1, Math.floor(this.root.clientWidth));
    const h = Math.max(1, Math.floor(this.root.clientHeight));
    if (w === this.width && h === this.height) return;
    this.width = w; this.height = h;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.fitCamera();
  }

  // Frame the neutral's bounding box (or frame_bounds) seen from the front (+Z), then apply the group's
  // orbit (azimuth, elevation), zoom and pan; pan is in units of the box height.
  fitCamera() {
    if (!this.bbox || !this.width) return;
    const THREE = this.THREE;
    const fb = this.model.frame_bounds;
    const box = fb && fb.length === 6 && fb.every(Number.isFinite)
      ? new THREE.Box3(new THREE.Vector3(fb[0], fb[1], fb[2]), new THREE.Vector3(fb[3], fb[4], fb[5])) : this.bbox;
    const c = box.getCenter(new THREE.Vector3());
    const s = box.getSize(new THREE.Vector3());
    const tanY = Math.tan((this.camera.fov * Math.PI) / 360);
    const tanX = tanY * this.camera.aspect;
    const margin = this.model.margin_factor;
    const dist = margin * Math.max(s.y / 2 / tanY, s.x / 2 / tanX) + s.z / 2;
    this.base = { center: c, dist, height: s.y };
    this.camera.near = dist / 100;
    this.camera.far = dist * 10;
    if (this.clock && this.clock.members.has(this)) this.clock.setZoom(this.clock.camera.zoom);  // the range is this mesh's too
    else this.updateCamera();
  }

  // The smallest shared zoom that keeps this camera outside the mesh's bounding sphere (plus the
  // near plane): the camera sits at base.dist * zoom from the box centre.
  minZoom() {
    if (!this.base || !this.bbox) return 0;
    const r = this.bbox.getBoundingSphere(new this.THREE.Sphere()).radius;
    return (1.02 * r + this.camera.near) / this.base.dist;
  }

  updateCamera() {
    if (!this.base) return;
    const cam = this.clock ? this.clock.camera : { azimuth: 0, elevation: 0, zoom: 1, panX: 0, panY: 0 };
    const { center, dist, height } = this.base;
    const d = dist * cam.zoom;
    const ce = Math.cos(cam.elevation);
    const dir = new this.THREE.Vector3(ce * Math.sin(cam.azimuth), Math.sin(cam.elevation), ce * Math.cos(cam.azimuth));
    this.camera.position.copy(center).addScaledVector(dir, d);
    this.camera.up.set(0, 1, 0);
    this.camera.lookAt(center);
    // pan in the camera plane
    const right = new this.THREE.Vector3().setFromMatrixColumn(this.camera.matrixWorld, 0);
    const up = new this.THREE.Vector3().setFromMatrixColumn(this.camera.matrixWorld, 1);
    const offset = right.multiplyScalar(-cam.panX * height).add(up.multiplyScalar(cam.panY * height));
    this.camera.position.add(offset);
    this.camera.updateProjectionMatrix();
    this.camera.updateMatrixWorld();
    this.requestRender();
  }

  // A small orbit control (written here rather than loading three's OrbitControls addon:
  // it needs 40 lines and the group sharing below). Left drag: orbit; right/shift drag: pan;
  // wheel: zoom; double click: reset. The camera state lives on the sync group's clock, so
  // side-by-side viewers turn together.
  // pick_mode "vertex": a plain left click on the mesh picks its vertex, a left drag that
  // starts on the mesh drags it (in the view plane); orbit with a left drag that starts off
  // the mesh, alt + left drag or a middle-button drag; pan and zoom as above.
  bindControls() {
    const cv = this.canvas;
    let drag = null;
    const onDown = (e) => {
      const plain = e.button === 0 && !e.altKey && !e.shiftKey && !e.ctrlKey && !e.metaKey;
      if (plain && this.model.pick_mode === "vertex") {
        const hit = this.pickAt(e.clientX, e.clientY);
        if (hit) {
          drag = { pick: hit, frame: this.clock.frame, x0: e.clientX, y0: e.clientY, moved: false, end: null };
          cv.setPointerCapture(e.pointerId);
          return;
        }
      }
      drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
      cv.setPointerCapture(e.pointerId);
    };
    const onMove = (e) => {
      if (!drag) return;
      if (drag.pick) {
        if (!drag.moved && Math.hypot(e.clientX - drag.x0, e.clientY - drag.y0) < DRAG_PX) return;
        drag.moved = true;
        drag.end = this.planePoint(e.clientX, e.clientY, drag.pick.position) || drag.end;
        if (drag.end) this.showDrag(drag.pick.position, drag.end);
        return;
      }
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      const cam = this.clock.camera;
      const h = this.height || 1;
      if (drag.pan) {
        cam.panX += (dx / h) * cam.zoom;
        cam.panY += (dy / h) * cam.zoom;
      } else {
        cam.azimuth -= (dx / h) * Math.PI;
        cam.elevation = Math.min(Math.max(cam.elevation + (dy / h) * Math.PI, -RIGHT_ANGLE * 0.95), RIGHT_ANGLE * 0.95);
      }
      this.clock.cameraChanged();
    };
    const onUp = (e) => {
      const d = drag;
      drag = null;
      try { cv.releasePointerCapture(e.pointerId); } catch (err) {}
      if (!d || !d.pick || e.type === "pointercancel") { if (d && d.pick) this.showDrag(null); return; }
      const p = d.pick.position;
      if (d.moved) {
        const end = this.planePoint(e.clientX, e.clientY, p) || d.end;
        this.showDrag(null);
        if (end) this.report("dragged", { vertex: d.pick.vertex, frame: d.frame, start: [p.x, p.y, p.z], end: [end.x, end.y, end.z] });
      } else {
        this.report("picked", { vertex: d.pick.vertex, frame: d.frame, position: [p.x, p.y, p.z] });
      }
    };
    const onWheel = (e) => {
      e.preventDefault();
      const cam = this.clock.camera;
      this.clock.setZoom(cam.zoom * Math.exp(e.deltaY * 0.001));
    };
    const onDbl = () => {
      Object.assign(this.clock.camera, { azimuth: 0, elevation: 0, zoom: 1, panX: 0, panY: 0 });
      this.clock.cameraChanged();
    };
    const onCtx = (e) => e.preventDefault();
    cv.addEventListener("pointerdown", onDown);
    cv.addEventListener("pointermove", onMove);
    cv.addEventListener("pointerup", onUp);
    cv.addEventListener("pointercancel", onUp);
    cv.addEventListener("wheel", onWheel, { passive: false });
    cv.addEventListener("dblclick", onDbl);
    cv.addEventListener("contextmenu", onCtx);
  }

  // -- model <-> viewer --------------------------------------------------------------------
  watch() {
    const m = this.model;
    m.on("frame", () => {
      if (this.reporting) return;
      const f = this.clock.clamp(m.frame);
      if (this.clock.isStaleEcho(m.frame)) {
        // the frame shown stands; after a pause, Python is told it again (the stale echo set
        // this model's frame to the older one)
        if (!this.clock.playing && f !== this.clock.frame) this.reportFrame(this.clock.frame);
        return;
      }
      this.clock.seek(f);
    });
    m.on("playing", () => { if (!this.reporting) this.clock.play(m.playing); });
    m.on("fps", () => this.clock.setFps(m.fps));
    m.on("loop", () => { this.clock.loop = m.loop; });
    m.on("weights", () => { this.endStream(); this.applyFrame(this.clock.frame); this.requestRender(); });
    // weights streamed as messages (a live stream: MeshViewer.stream_weights: K float32,
    // little-endian, base64), shown at once, decoded into buffers kept per view (no typed-array
    // allocation per message); blended and drawn at most once per
    // animation frame, in that frame (the latest weights win); a hidden view only keeps them
    m.on("msg:custom", (data) => {
      if (!data || typeof data.w32 !== "string") return;
      const bin = atob(data.w32);
      if (bin.length !== 4 * this.K) return;
      if (!this.streamBytes || this.streamBytes.length !== 4 * this.K) {
        this.streamBytes = new Uint8Array(4 * this.K);
        this.streamF32 = new Float32Array(this.streamBytes.buffer);
      }
      for (let i = 0; i < bin.length; i++) this.streamBytes[i] = bin.charCodeAt(i);
      this.receiveStreamed(this.streamF32);
    });
    m.on(["track", "track_url"], () => this.reloadTrack());
    m.on(["geometry_url", "geometry"], () => this.reloadGeometry());
    m.on(["marker_vertices", "marker_weights", "marker_track", "marker_radius"], () => {
      this.setMarkers(); this.setTrack(); this.showFrame(this.clock.frame, false);
    });
    m.on("show_markers", () => { if (this.markers) this.markers.visible = m.show_markers; this.requestRender(); });
    m.on("marker_color", () => { this.markerMaterial.color.set(m.marker_color); this.requestRender(); });
    m.on(["colors", "mesh_color"], () => { this.setColors(); this.requestRender(); });
    m.on("background_color", () => { this.scene.background.set(m.background_color); this.requestRender(); });
    m.on(["margin_factor", "frame_bounds"], () => this.fitCamera());
    m.on(["gaps"], () => { if (this.clock) this.showFrame(this.clock.frame, false); });
    m.on(["highlight", "highlight_radius"], () => { this.setHighlight(); this.requestRender(); });
    m.on("highlight_color", () => {
      this.highlightMaterial.color.set(m.highlight_color); this.dragMaterial.color.set(m.highlight_color); this.requestRender();
    });
    m.on("uvs", () => { this.setUvs(); this.updateMaterial(); this.requestRender(); });
    m.on("normal_map", () => { this.setNormalMap(); this.requestRender(); });
    m.on("offsets", () => { this.setOffsets(); this.applyFrame(this.clock.frame); this.requestRender(); });
    m.on("normal_map_space", () => { this.updateMaterial(); this.requestRender(); });
    m.on("pick_mode", () => { this.canvas.style.cursor = m.pick_mode === "vertex" ? "crosshair" : ""; });
    m.on("remove", () => this.dispose());
  }

  // Diagnostics used by the browser tests (window.__faceRetarget.viewers[label]); nothing
  // here talks to Python.
  api() {
    return {
      label: this.label,
      get K() { return this.self.K; },
      get V() { return this.self.V; },
      get frame() { return this.self.clock.frame; },
      get playing() { return this.self.clock.playing; },
      get nFrames() { return this.self.nFrames; },
      self: this,
      shapeNames: () => Array.from(this.model.shape_names || []),
      influences: () => Array.from(this.current || []),
      gpuInfluences: () => Array.from((this.mesh && this.mesh.morphTargetInfluences) || []),
      markerPositions: () => Array.from(this.markerPos || []),
      // the mesh as shown when it is blended in JS (blend cpu, or offsets set); null while
      // morph targets blend it on the gpu (it never leaves the shader)
      positions: () => (!this.morphing && this.mesh ? Array.from(this.mesh.geometry.getAttribute("position").array) : null),
      normals: () => (!this.morphing && this.mesh ? Array.from(this.mesh.geometry.getAttribute("normal").array) : null),
      // the weights shown blended from scratch over the dense deltas (blendDense), in new arrays:
      // what the incrementally kept buffers must equal up to float32 rounding
      denseBlend: () => {
        if (!this.mesh || !this.V) return null;
        const P = new Float32Array(3 * this.V), Nn = new Float32Array(3 * this.V);
        this.blendDense(this.current, P, Nn);
        return { positions: Array.from(P), normals: Array.from(Nn) };
      },
      visible: () => this.visible,
      // the streamed drawing's render scale now (adaptScale) and the canvas's drawing buffer size
      renderScale: () => ({ scale: RENDER_SCALES[this.scaleStep], width: this.canvas.width, height: this.canvas.height,
                            frameMs: this.frameMs || null, changes: this.stats.scaleChanges || 0 }),
      // the JS blend of a sequence of streamed weights (lists of K), ms per blend, the best of
      // `reps` runs: ours (incremental, deferring invisible changes) and ref
      // (window.__faceRetargetFullBlend: from scratch); blend "cpu" only. The view is
      // re-blended as it was afterwards.
      benchBlend: (ws, reps = 3) => {
        if (this.morphing || !this.mesh) return null;
        const seq = ws.map((w) => Float32Array.from(w));
        const saved = window.__faceRetargetFullBlend, out = {};
        for (const full of [false, true]) {
          window.__faceRetargetFullBlend = full;
          let best = Infinity;
          for (let r = 0; r < reps; r++) {
            this.blendedW = null;
            const t = performance.now();
            for (const w of seq) this.blendCpu(w, true);
            best = Math.min(best, (performance.now() - t) / seq.length);
          }
          out[full ? "ref" : "ours"] = best;
        }
        window.__faceRetargetFullBlend = saved;
        this.blendedW = null;
        this.blended = null;
        this.applyFrame(this.clock.frame);
        this.requestRender();
        return out;
      },
      // weights (K) as a streamed message brings them (MeshViewer.stream_weights), drawn now;
      // null: back to the track
      stream: (w) => {
        if (w === null) { this.endStream(); this.applyFrame(this.clock.frame); this.renderNow(); return null; }
        this.receiveStreamed(w);
        if (this.streamPending) { cancelAnimationFrame(this.streamPending); this.drawStreamed(); }
        return { full: this.stats.fullBlends || 0, incremental: this.stats.incrementalBlends || 0 };
      },
      offsets: () => (this.offsets ? Array.from(this.offsets) : null),
      showMarkers: (on) => { if (this.markers) this.markers.visible = on && this.model.show_markers; this.renderNow(); },
      // show probe weights (K floats) or null to go back to the track, render at once
      probe: (w) => {
        this.override = w ? Float32Array.from(w) : null;
        this.applyFrame(this.clock.frame);
        this.renderNow();
      },
      // render now and read the drawing buffer back (forces the GPU to finish)
      pixels: () => {
        this.renderNow();
        const gl = this.renderer.getContext();
        const w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
        const buf = new Uint8Array(w * h * 4);
        gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, buf);
        return { width: w, height: h, data: buf };
      },
      // render n frames of the track (from `start`) back to back, each forced to finish with
      // a 1-pixel readPixels: the sustainable frame time, independent of the capture fps
      benchRender: (n, start = 0) => {
        const gl = this.renderer.getContext();
        const px = new Uint8Array(4);
        const t = performance.now();
        for (let i = 0; i < n; i++) {
          this.applyFrame((start + i) % this.nFrames);
          this.renderNow();
          gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
        }
        const ms = (performance.now() - t) / n;
        this.applyFrame(this.clock.frame);
        this.requestRender();
        return ms;
      },
      // picking as a click would do it, without telling Python (client coordinates)
      pickAt: (x, y) => {
        const h = this.pickAt(x, y);
        return h && { vertex: h.vertex, position: h.position.toArray(), point: h.point.toArray(), face: h.face };
      },
      vertexPositions: (ids) => ids.map((v) => this.vertexPosition(v, new this.THREE.Vector3()).toArray()),
      highlightPositions: () => (this.highlights ? this.highlightIds.map((v, i) => {
        const m = new this.THREE.Matrix4();
        this.highlights.getMatrixAt(i, m);
        return new this.THREE.Vector3().setFromMatrixPosition(m).toArray();
      }) : []),
      // the camera as rendered: column-major view and projection matrices, canvas CSS size
      camera: () => {
        this.camera.updateMatrixWorld();
        const r = this.canvas.getBoundingClientRect();
        return { view: this.camera.matrixWorldInverse.elements.slice(), projection: this.camera.projectionMatrix.elements.slice(),
                 position: this.camera.position.toArray(), left: r.left, top: r.top, width: r.width, height: r.height };
      },
      info: () => ({
        webgl2: this.renderer.capabilities.isWebGL2 !== false,
        renderer: this.rendererName,
        maxTextureSize: this.renderer.capabilities.maxTextureSize,
        revision: this.THREE.REVISION,
        blend: this.blend, shading: this.shading, software: this.software,
        morphTargets: Boolean(this.morphing), offsets: Boolean(this.offsets),
        material: this.material.userData.kind,
        normalMap: this.material.normalMap ? { width: this.material.normalMap.image.width, height: this.material.normalMap.image.height,
                                               space: this.model.normal_map_space, updates: this.stats.normalMapUpdates || 0,
                                               ms: this.stats.normalMapMs } : null,
        uvs: Boolean(this.hasUvs),
        V: this.V, K: this.K, M: this.M, T: this.nFrames,
        width: this.width, height: this.height,
        normalsMs: this.stats.normalsMs, offsetNormalsMs: this.stats.offsetNormalsMs,
        geometryBuilds: this.stats.geometryBuilds, offsetUpdates: this.stats.offsetUpdates,
      }),
    };
  }

  dispose() {
    if (this.disposed) return;
    this.disposed = true;
    if (this.pendingRender !== null) cancelAnimationFrame(this.pendingRender);
    if (this.clock) this.clock.leave(this); // not joined yet while the mesh was still loading
    this.resizeObserver.disconnect();
    this.intersection.disconnect();
    if (this.streamPending) cancelAnimationFrame(this.streamPending);
    if (this.mesh) this.disposeGeometry();
    if (this.markers) this.markers.geometry.dispose();
    this.material.dispose();
    if (this.normalTexture) this.normalTexture.dispose();
    this.markerMaterial.dispose();
    if (this.highlights) this.highlights.geometry.dispose();
    this.highlightMaterial.dispose();
    this.dragLine.geometry.dispose();
    this.dragEnd.geometry.dispose();
    this.dragMaterial.dispose();
    this.renderer.dispose();
    if (REGISTRY.viewers[this.label] && REGISTRY.viewers[this.label].self === this) delete REGISTRY.viewers[this.label];
  }
}

export async function render({ model, el, view }) {
  if (view && view.__faceRetargetViewer) view.__faceRetargetViewer.dispose();
  let THREE;
  try {
    THREE = await import("three");
  } catch (err) {
    const msg = document.createElement("div");
    msg.style.cssText = "padding:1em;color:#b00;font:13px sans-serif;";
    msg.textContent =
      "The 3D viewer could not load three.js from this server (" + err + "). " +
      "Serve the app with the three.js route: `python scripts/viewer_demo.py`, " +
      "`panel serve app.py --plugins dashboard.assets`, and run `npm ci` at the repository root.";
    el.replaceChildren(msg);
    return;
  }
  const viewer = new Viewer(THREE, model, el, view);
  if (view) view.__faceRetargetViewer = viewer;
}
