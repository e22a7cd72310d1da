// lungdeform browser viewer: both lungs breathing in real time, deformation on the GPU.
//
// The model is /model.glb written by lungdeform.export: end-exhale mesh + 5 morph targets per lung
// (target 0 = the model's own tidal displacement, 1-4 = the orientation basis). Every frame the CPU
// computes 5 weights per lung (a constant cost, whatever the vertex count) and three.js blends the
// targets in its vertex shader. With `lungdeform view MODEL --trace TRACE [--predict-ms H]` the
// server's /trace.json holds a recorded trace with the streaming estimator's measured and predicted
// volume per sample (trace.ts); the preset 'trace' plays it in trace time. URL options: ?clock=manual (time moves only through the test API),
// ?deform=cpu (blend on the CPU and re-upload positions each frame: the path the GPU one replaces).
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import './style.css';
import { GRAVITY, isMovable, LungWeights, MarkerMotion, normalize, type LungMeta, type Marker, type Vec3 } from './physics';
import { loadPresets, loopDuration, sampledCurve, volumeAt, type Curve, type PresetSet } from './curves';
import { colourise, legendGradient } from './overlay';
import { FrameStats } from './stats';
import { beamText, GATE_COLOURS, GateChart, gateAt, gateText, latencyText, loadTrace, pushEvent, sampleIndex, StripChart, traceTime, traceVolumeAt, valuesText, type TraceSeries } from './trace';
import { setupXR } from './xr';

const params = new URLSearchParams(location.search);
const manualClock = params.get('clock') === 'manual';
const deformMode: 'gpu' | 'cpu' = params.get('deform') === 'cpu' ? 'cpu' : 'gpu';
const BACKGROUND = new THREE.Color(0x0f1318);

const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T;
const canvas = $('view') as HTMLCanvasElement;
const statusEl = $('status');

interface Lung {
  name: string;
  mesh: THREE.Mesh;
  meta: LungMeta;
  weights: LungWeights;
  influences: number[];
  targets: Float32Array[]; // CPU copies of the 5 targets (CPU path only; empty on the GPU path)
  base: Float32Array; // end-exhale positions (CPU path only)
  markers: MarkerMotion | null; // this lung's markers, packed once (LPS mm)
  spheres: THREE.Mesh[]; // one per marker, in the order of markers
}

const state = {
  t: 0,
  playing: true,
  curve: null as Curve | null,
  /** Playing the server's trace (preset 'trace'): state.curve is null then. */
  trace: null as TraceSeries | null,
  tidalMl: 500,
  rateBpm: 15,
  gain: 1,
  orientation: 'model' as string,
  gravity: 'model' as Vec3 | 'model',
  overlay: 'none',
  markers: false,
  dvMl: 0,
};

const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, powerPreference: 'high-performance' });
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
const scene = new THREE.Scene();
scene.background = BACKGROUND;
const camera = new THREE.PerspectiveCamera(30, 1, 0.01, 20);
const controls = new OrbitControls(camera, canvas);
scene.add(new THREE.HemisphereLight(0xdfe9ff, 0x302820, 1.4));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(0.6, 1.0, 1.2);
scene.add(sun);

const lungs: Lung[] = [];
let curves: Curve[] = [];
let presetSet: PresetSet | null = null;
let served: TraceSeries | null = null; // /trace.json, null when the server plays no trace
let strip: StripChart | null = null;
let gateStrip: GateChart | null = null; // with a gate (--predict-ms > 0): window, interval band, beam
let root: THREE.Object3D | null = null;
let arrow: THREE.ArrowHelper | null = null;
const stats = new FrameStats();
let lastFrame = performance.now();

function resize(): void {
  const w = canvas.clientWidth || 800, h = canvas.clientHeight || 600;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener('resize', resize);

// ------------------------------------------------------------------ per-frame work (O(1) on the GPU path)
function loop(): number {
  if (state.trace) return state.trace.durationS || 1;
  return state.curve ? loopDuration(state.curve, state.rateBpm) : 4;
}

function update(): void {
  const curve = state.curve;
  state.dvMl = state.trace ? traceVolumeAt(state.trace, state.t, state.tidalMl)
    : curve ? volumeAt(curve, state.t, state.tidalMl, state.rateBpm) : 0;
  for (const lung of lungs) {
    lung.weights.weights(lung.meta.share * state.dvMl, state.gain, lung.influences);
    if (deformMode === 'gpu') {
      const infl = lung.mesh.morphTargetInfluences!;
      for (let k = 0; k < 5; k++) infl[k] = lung.influences[k];
    } else {
      cpuDeform(lung);
    }
    if (state.markers) placeMarkers(lung);
  }
}

/** CPU path: x = p + sum_k w_k T_k for every vertex, then a full upload (grows with n). */
function cpuDeform(lung: Lung): void {
  const attr = lung.mesh.geometry.getAttribute('position') as THREE.BufferAttribute;
  const pos = attr.array as Float32Array;
  pos.set(lung.base);
  for (let k = 0; k < 5; k++) {
    const w = lung.influences[k];
    if (w === 0) continue;
    const t = lung.targets[k];
    for (let i = 0; i < pos.length; i++) pos[i] += w * t[i];
  }
  attr.needsUpdate = true;
}

/**
 * Markers move with the lung's interior field: x = p + lambda * w, w their displacement per unit
 * weight of target 0 (glb extras), lambda that target's weight now (three multiply-adds per marker,
 * no allocation). Re-oriented (targets 1-4), lambda is the tidal weight for the same volume: the
 * tidal-vector approximation (docs/VIEWER.md).
 */
function placeMarkers(lung: Lung): void {
  const motion = lung.markers;
  if (!motion) return;
  const lambda = lung.weights.native ? lung.influences[0]
    : lung.weights.tidalWeight(lung.meta.share * state.dvMl, state.gain);
  const x = motion.positions(lambda);
  for (let i = 0; i < motion.count; i++) lung.spheres[i].position.set(x[3 * i], x[3 * i + 1], x[3 * i + 2]);
}

function frame(now: number): void {
  const dt = Math.min((now - lastFrame) / 1000, 0.25);
  lastFrame = now;
  const t0 = performance.now();
  if (state.playing && !manualClock) state.t += dt;
  update();
  renderer.render(scene, camera);
  stats.record(performance.now() - t0, now);
  showBeam();
  if (stats.due(now)) showReadout();
}

/** The trace HUD: the sample shown now (measured vs predicted) and the strip chart around it. */
function showTrace(): void {
  if (!state.trace) return;
  $('trace-values').textContent = valuesText(state.trace, state.t);
  strip?.draw(state.trace, state.t);
  if (!gateStrip) return;
  showBeam();
  $('gate-values').textContent = gateText(state.trace, state.t);
  gateStrip.draw(state.trace, state.t);
}

let beamShown = -1; // the indicator's state: -1 not yet set, 0 off, 1 on

/** The BEAM ON/OFF indicator, every frame (a beam indicator must not lag): the DOM is touched only
 * when the decision of the sample shown changes. */
function showBeam(): void {
  const g = state.trace?.gate;
  if (!g || !state.trace || state.trace.n === 0) return;
  const on = g.beam[sampleIndex(state.trace.t, traceTime(state.trace, state.t), state.trace.n)];
  if (on === beamShown) return;
  beamShown = on;
  const beam = $('beam');
  beam.textContent = beamText(state.trace, state.t);
  beam.classList.toggle('on', on === 1);
  beam.classList.toggle('off', on !== 1);
}

// ------------------------------------------------------------------ model loading
async function loadModel(): Promise<void> {
  const gltf = await new GLTFLoader().loadAsync('model.glb');
  root = gltf.scene;
  scene.add(root);
  const extras = (gltf.userData?.lungdeform ?? {}) as { curve?: { t_s: number[]; volume_ml: number[]; source: string }; markers?: Partial<Marker>[] };
  root.traverse((obj) => {
    const mesh = obj as THREE.Mesh;
    const meta = mesh.isMesh ? (mesh.userData?.lungdeform as LungMeta | undefined) : undefined;
    if (!meta) return;
    const geom = mesh.geometry;
    const morph = geom.morphAttributes.position ?? [];
    if (morph.length !== 5) throw new Error(`lung ${meta.lung}: expected 5 morph targets, found ${morph.length}`);
    const cpu = deformMode === 'cpu';
    const targets = cpu ? morph.map((a) => Float32Array.from(a.array as ArrayLike<number>)) : [];
    const base = cpu ? Float32Array.from(geom.getAttribute('position').array as ArrayLike<number>) : new Float32Array(0);
    if (cpu) {
      geom.morphAttributes = {};
      mesh.morphTargetInfluences = undefined;
      (geom.getAttribute('position') as THREE.BufferAttribute).setUsage(THREE.DynamicDrawUsage);
    }
    mesh.frustumCulled = false;
    const material = (mesh.material as THREE.MeshStandardMaterial).clone();
    mesh.material = material;
    lungs.push({ name: meta.lung, mesh, meta, weights: new LungWeights(meta), influences: [0, 0, 0, 0, 0],
                 targets, base, markers: null, spheres: [] });
  });
  if (lungs.length === 0) throw new Error('model.glb holds no lungdeform lungs (mesh extras missing)');
  addMarkers(extras.markers ?? []);
  presetSet = await loadPresets((url) => fetch(url));
  curves = [];
  if (extras.curve && extras.curve.t_s.length > 1) {
    curves.push(sampledCurve('model', 'Model curve (export)', extras.curve.t_s, extras.curve.volume_ml,
                             extras.curve.source));
  }
  curves.push(...presetSet.curves);
  const feed = await loadTrace((url) => fetch(url));
  served = feed?.series ?? null;
  if (feed && served) {
    $('trace-panel').hidden = false;
    $('trace-source').textContent = feed.liveUrl ? `live from ${served.source}`
      : `${served.source} (${served.n} samples, ${served.durationS.toFixed(1)} s)`;
    if (feed.liveUrl) listen(served, feed.liveUrl);
    $('latency').textContent = latencyText(served);
    strip = new StripChart($('strip') as HTMLCanvasElement);
    if (served.gate) {
      $('gate').hidden = false;
      $('gate-rule').textContent = `gate: window ${served.gate.window}, beam on when ${served.gate.rule}`;
      gateStrip = new GateChart($('gate-strip') as HTMLCanvasElement);
    }
  }
  const note = $('presets-note');
  note.textContent = presetSet.note;
  note.classList.toggle('warning', presetSet.origin !== 'server');
  fitCamera();
  addGravityArrow();
}

/** Live: each Server-Sent Event is one sample (pushed into the series' buffers); 'end' when input ends. */
function listen(series: TraceSeries, url: string): void {
  const source = new EventSource(url);
  source.onmessage = (e) => { try { pushEvent(series, e.data); } catch (err) { showError(err); } };
  source.addEventListener('end', () => { source.close(); $('trace-source').textContent = `live from ${series.source}: input ended`; });
}

function addMarkers(markers: Partial<Marker>[]): void {
  const geo = new THREE.SphereGeometry(4, 16, 12); // mm, in the lung's LPS frame
  // markers of an older export (glb schema 1: anchor vertices, no tidal_mm) cannot follow the interior field
  const movable = markers.filter(isMovable).filter((m) => lungs.some((l) => l.name === m.lung));
  for (const lung of lungs) {
    const own = movable.filter((m) => m.lung === lung.name);
    if (own.length === 0) continue;
    lung.markers = new MarkerMotion(own);
    for (const m of own) {
      const sphere = new THREE.Mesh(geo, new THREE.MeshStandardMaterial({ color: 0xffd54f, emissive: 0x553300 }));
      sphere.position.set(...m.position_mm);
      sphere.visible = false;
      sphere.renderOrder = 2;
      lung.mesh.add(sphere);
      lung.spheres.push(sphere);
    }
  }
  const skipped = markers.length - movable.length;
  $('marker-count').textContent = markers.length === 0 ? '(none in model)'
    : `(${movable.length})` + (skipped ? `, ${skipped} not shown: older export, re-export the model` : '');
  ($('markers') as HTMLInputElement).disabled = movable.length === 0;
}

function fitCamera(): void {
  const box = new THREE.Box3().setFromObject(root!);
  const centre = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3());
  const dist = (1.25 * Math.max(size.x, size.y)) / (2 * Math.tan((camera.fov * Math.PI) / 360));
  camera.position.set(centre.x, centre.y, centre.z + dist); // anterior view (glTF +Z = anterior)
  camera.near = dist / 50; camera.far = dist * 10;
  camera.updateProjectionMatrix();
  controls.target.copy(centre);
  controls.update();
}

function addGravityArrow(): void {
  const box = new THREE.Box3();
  for (const l of lungs) { l.mesh.geometry.computeBoundingBox(); box.union(l.mesh.geometry.boundingBox!); }
  const c = box.getCenter(new THREE.Vector3());
  arrow = new THREE.ArrowHelper(new THREE.Vector3(0, 1, 0), new THREE.Vector3(c.x, c.y, box.max.z + 25), 60, 0x80cbc4, 15, 8);
  root!.add(arrow); // in LPS mm like the meshes
  refreshArrow();
}

function refreshArrow(): void {
  if (!arrow) return;
  const g = state.gravity === 'model' ? lungs[0].meta.gravity : state.gravity;
  arrow.setDirection(new THREE.Vector3(...normalize(g)));
}

// ------------------------------------------------------------------ settings (shared by UI and API)
function setPreset(name: string): void {
  if (name === 'trace' && served) {
    state.curve = null;
    state.trace = served;
    state.tidalMl = served.tidalMl; // the estimator's own volumes; the control rescales them
    $('preset-source').textContent = served.live ? `live feed from ${served.source}: the newest sample is shown`
      : `trace ${served.source}, played in trace time`;
    syncUI();
    showTrace();
    return;
  }
  const c = curves.find((x) => x.name === name);
  if (!c) throw new Error(`unknown preset '${name}' (have ${presetNames().join(', ')})`);
  state.curve = c;
  state.trace = null;
  state.tidalMl = c.tidalMl;
  state.rateBpm = c.rateBpm;
  $('preset-source').textContent = c.source;
  syncUI();
}

/** The preset menu: the served trace first (when there is one), then the curves. */
function presetNames(): string[] { return [...(served ? ['trace'] : []), ...curves.map((c) => c.name)]; }

function setOrientation(o: string | Vec3): void {
  if (Array.isArray(o)) {
    state.orientation = 'custom';
    state.gravity = normalize(o as Vec3);
  } else if (o === 'model') {
    state.orientation = 'model'; state.gravity = 'model';
  } else if (o in GRAVITY) {
    state.orientation = o; state.gravity = GRAVITY[o];
  } else {
    throw new Error(`unknown orientation '${o}'`);
  }
  const stuck = lungs.filter((l) => !l.weights.setGravity(state.gravity)).map((l) => l.name);
  statusEl.classList.toggle('error', stuck.length > 0);
  statusEl.textContent = stuck.length
    ? `${state.orientation}: the model's force basis does not grow the ${stuck.join(' and ')} lung (dV/ds ≤ 0); shown at end-exhale`
    : loadedText();
  refreshArrow();
  if (state.overlay === 'force') setOverlay('force');
  syncUI();
}

function setOverlay(kind: string): void {
  state.overlay = kind;
  let range: [number, number] | null = null;
  for (const l of lungs) range = colourise(l.mesh, kind, l.weights.fieldWeights(), range);
  // second pass so both lungs share one colour scale
  if (kind !== 'none') for (const l of lungs) colourise(l.mesh, kind, l.weights.fieldWeights(), range, true);
  $('legend').style.background = kind === 'none' ? 'none' : legendGradient();
  $('legend').title = range ? `${range[0].toPrecision(3)} … ${range[1].toPrecision(3)}` : '';
  syncUI();
}

function setMarkers(on: boolean): void {
  state.markers = on;
  for (const l of lungs) {
    for (const sphere of l.spheres) sphere.visible = on;
    const mat = l.mesh.material as THREE.MeshStandardMaterial;
    mat.transparent = on; mat.opacity = on ? 0.45 : 1; mat.depthWrite = !on;
    mat.needsUpdate = true;
  }
  syncUI();
}

// ------------------------------------------------------------------ UI
function syncUI(): void {
  ($('preset') as HTMLSelectElement).value = state.trace ? 'trace' : state.curve?.name ?? '';
  ($('rate') as HTMLInputElement).disabled = state.trace !== null; // a trace plays in its own time
  ($('tidal') as HTMLInputElement).value = String(state.tidalMl);
  $('tidal-out').textContent = state.tidalMl.toFixed(0);
  ($('rate') as HTMLInputElement).value = String(state.rateBpm);
  $('rate-out').textContent = state.rateBpm.toFixed(1);
  ($('gain') as HTMLInputElement).value = String(state.gain);
  $('gain-out').textContent = String(state.gain);
  ($('orientation') as HTMLSelectElement).value = state.orientation;
  $('custom-g').hidden = state.orientation !== 'custom';
  ($('overlay') as HTMLSelectElement).value = state.overlay;
  ($('markers') as HTMLInputElement).checked = state.markers;
  $('play').textContent = state.playing ? 'Pause' : 'Play';
}

function bindUI(): void {
  const sel = $('preset') as HTMLSelectElement;
  const traceOption = served ? [new Option(`Trace (${served.predictMs > 0 ? `${served.predictMs} ms ahead` : 'measured'})`, 'trace')] : [];
  sel.replaceChildren(...traceOption, ...curves.map((c) => new Option(c.label, c.name)));
  sel.onchange = () => setPreset(sel.value);
  const tidal = $('tidal') as HTMLInputElement;
  tidal.oninput = () => { state.tidalMl = Number(tidal.value); syncUI(); };
  const rate = $('rate') as HTMLInputElement;
  rate.oninput = () => {
    const phase = (state.t / loop()) % 1;
    state.rateBpm = Number(rate.value);
    state.t = phase * loop(); // keep the phase when the rate changes
    syncUI();
  };
  const gain = $('gain') as HTMLInputElement;
  gain.oninput = () => { state.gain = Number(gain.value); syncUI(); };
  const orient = $('orientation') as HTMLSelectElement;
  const custom = () => setOrientation([Number(($('gx') as HTMLInputElement).value),
    Number(($('gy') as HTMLInputElement).value), Number(($('gz') as HTMLInputElement).value)]);
  orient.onchange = () => (orient.value === 'custom' ? custom() : setOrientation(orient.value));
  for (const id of ['gx', 'gy', 'gz']) $(id).onchange = () => { try { custom(); } catch (e) { showError(e); } };
  const overlay = $('overlay') as HTMLSelectElement;
  overlay.onchange = () => setOverlay(overlay.value);
  const markers = $('markers') as HTMLInputElement;
  markers.onchange = () => setMarkers(markers.checked);
  $('play').onclick = () => { state.playing = !state.playing; syncUI(); };
  const scrub = $('scrub') as HTMLInputElement;
  scrub.oninput = () => { state.playing = false; state.t = (Number(scrub.value) / 1000) * loop(); syncUI(); };
  const lbl = lungs[0].meta.gravity;
  const native = Object.entries(GRAVITY).find(([, g]) => g.every((x, i) => Math.abs(x - lbl[i]) < 1e-6));
  orient.options[0].text = `model (as built: ${native ? native[0] : lbl.map((x) => x.toFixed(2)).join(', ')})`;
}

function showReadout(): void {
  const s = stats.summary();
  const lines = [
    `fps ${s.fps.toFixed(1)}   frame ${s.frameMs.toFixed(2)} ms (CPU, mean)`,
    `interval ${s.intervalMs.toFixed(1)} ms   deform ${deformMode.toUpperCase()}`,
    `t ${state.t.toFixed(2)} s   ΔV ${state.dvMl.toFixed(0)} mL (both lungs)`,
    ...lungs.map((l) => `${l.name}: ${(l.meta.volume_ee_ml + l.meta.share * state.dvMl).toFixed(0)} mL, ${l.meta.n_vertices} vertices`),
  ];
  $('readout').textContent = lines.join('\n');
  const scrub = $('scrub') as HTMLInputElement;
  if (state.playing) scrub.value = String(Math.round(((state.t / loop()) % 1) * 1000));
  $('clock').textContent = manualClock ? 'clock: manual (test)' : '';
  showTrace();
}

function loadedText(): string {
  return `${lungs.length} lungs, ${lungs.reduce((n, l) => n + l.meta.n_vertices, 0)} vertices`;
}

function showError(e: unknown): void {
  statusEl.textContent = `error: ${e instanceof Error ? e.message : String(e)}`;
  statusEl.classList.add('error');
}

// ------------------------------------------------------------------ test and benchmark API
function renderOnce(): void { update(); renderer.render(scene, camera); showTrace(); }

const snapshots = new Map<string, { rgb: Uint8Array; mask: Uint8Array }>();

/** Render now and keep the picture and its silhouette (pixels unlike the background) under key. */
function snapshot(key: string) {
  renderOnce();
  const gl = renderer.getContext();
  const w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
  const px = new Uint8Array(w * h * 4);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
  const hex = BACKGROUND.getHex(); // sRGB, as the canvas shows it
  const bg = [(hex >> 16) & 255, (hex >> 8) & 255, hex & 255];
  const mask = new Uint8Array(w * h);
  const rgb = new Uint8Array(w * h * 3);
  let on = 0;
  for (let i = 0; i < w * h; i++) {
    const r = px[4 * i], g = px[4 * i + 1], b = px[4 * i + 2];
    rgb[3 * i] = r; rgb[3 * i + 1] = g; rgb[3 * i + 2] = b;
    const d = Math.max(Math.abs(r - bg[0]), Math.abs(g - bg[1]), Math.abs(b - bg[2]));
    if (d > 12) { mask[i] = 1; on++; }
  }
  snapshots.set(key, { rgb, mask });
  return { width: w, height: h, silhouettePixels: on };
}

/** Pixels whose silhouette membership differs, and pixels whose colour differs by more than 8/255. */
function diff(a: string, b: string) {
  const A = snapshots.get(a), B = snapshots.get(b);
  if (!A || !B) throw new Error(`no snapshot ${A ? b : a}`);
  let silhouette = 0, colour = 0;
  for (let i = 0; i < A.mask.length; i++) {
    if (A.mask[i] !== B.mask[i]) silhouette++;
    const d = Math.max(Math.abs(A.rgb[3 * i] - B.rgb[3 * i]), Math.abs(A.rgb[3 * i + 1] - B.rgb[3 * i + 1]),
                       Math.abs(A.rgb[3 * i + 2] - B.rgb[3 * i + 2]));
    if (d > 8) colour++;
  }
  return { silhouette, colour };
}

/** Frame times with a forced GPU sync (1-pixel readPixels) after each frame. */
function bench(frames = 60, warmup = 5) {
  const gl = renderer.getContext();
  const px = new Uint8Array(4);
  const wasPlaying = state.playing;
  state.playing = false;
  const step = () => { state.t += 1 / 60; };
  for (let i = 0; i < warmup; i++) { step(); renderOnce(); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px); }
  const total: number[] = [];
  for (let i = 0; i < frames; i++) {
    const a = performance.now();
    step();
    update();
    renderer.render(scene, camera);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    total.push(performance.now() - a);
  }
  // the per-frame CPU work of the deformation alone (weights; on the CPU path also the blend),
  // timed over repeated batches: performance.now() is coarsened to 0.1 ms in browsers
  const cpu: number[] = [];
  for (let r = 0; r < 5; r++) {
    let reps = 0;
    const a = performance.now();
    do { step(); update(); reps++; } while (performance.now() - a < 50);
    cpu.push((performance.now() - a) / reps);
  }
  state.playing = wasPlaying;
  const stat = (x: number[]) => {
    const s = [...x].sort((p, q) => p - q);
    return { median: s[s.length >> 1], mean: x.reduce((p, q) => p + q, 0) / x.length, p95: s[Math.floor(0.95 * (s.length - 1))] };
  };
  return { frames, deform: deformMode, vertices: lungs.reduce((n, l) => n + l.meta.n_vertices, 0),
           frameMs: stat(total), deformCpuMs: stat(cpu), renderer: rendererName(),
           width: gl.drawingBufferWidth, height: gl.drawingBufferHeight };
}

function rendererName(): string {
  const gl = renderer.getContext();
  const ext = gl.getExtension('WEBGL_debug_renderer_info');
  return String(ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER));
}

const api = {
  ready: null as unknown as Promise<object>,
  info: () => ({ lungs: lungs.map((l) => ({ name: l.name, vertices: l.meta.n_vertices, share: l.meta.share })),
                 markers: lungs.reduce((n, l) => n + l.spheres.length, 0),
                 presets: presetNames(), presetOrigin: presetSet?.origin, presetNote: presetSet?.note,
                 deform: deformMode, manualClock, renderer: rendererName() }),
  state: () => ({ t: state.t, dvMl: state.dvMl, playing: state.playing, preset: state.curve?.name, tidalMl: state.tidalMl,
                  rateBpm: state.rateBpm, orientation: state.orientation, overlay: state.overlay, loopS: loop(),
                  trace: state.trace ? { index: sampleIndex(state.trace.t, traceTime(state.trace, state.t), state.trace.n), n: state.trace.n,
                                         latency: $('latency').textContent, values: $('trace-values').textContent,
                                         gate: gateAt(state.trace, state.t), beam: $('beam').textContent, beamClass: $('beam').className,
                                         gateValues: $('gate-values').textContent } : null,
                  weights: Object.fromEntries(lungs.map((l) => [l.name, [...l.influences]])) }),
  setTime: (t: number) => { state.t = t; state.playing = false; syncUI(); },
  setPhase: (phase: number) => { state.t = phase * loop(); state.playing = false; syncUI(); },
  play: () => { state.playing = true; syncUI(); },
  pause: () => { state.playing = false; syncUI(); },
  setPreset, setOrientation, setOverlay, setMarkers,
  setTidal: (ml: number) => { state.tidalMl = ml; syncUI(); },
  setRate: (bpm: number) => { state.rateBpm = bpm; syncUI(); },
  setGain: (g: number) => { state.gain = g; syncUI(); },
  renderOnce, snapshot, diff, bench, stats: () => stats.summary(),
  /** Pixels of the gate strip in each of its colours (window, band, beam on/off): what is drawn. */
  gatePixels: () => {
    const c = $('gate-strip') as HTMLCanvasElement;
    const px = c.getContext('2d')!.getImageData(0, 0, c.width, c.height).data;
    const counts: Record<string, number> = {};
    for (const [name, hex] of Object.entries(GATE_COLOURS)) {
      const v = parseInt(hex.slice(1), 16), r = v >> 16, g = (v >> 8) & 255, b = v & 255;
      let n = 0;
      for (let i = 0; i < px.length; i += 4) if (px[i] === r && px[i + 1] === g && px[i + 2] === b) n++;
      counts[name] = n;
    }
    return counts;
  },
  /** Marker positions per lung (LPS mm, 3 per marker) as last placed (while markers are shown). */
  markerPositions: () => Object.fromEntries(lungs.map((l) => [l.name, l.markers ? Array.from(l.markers.out) : []])),
  /** Sum of the position buffers' versions: constant on the GPU path (no per-frame vertex upload). */
  positionUploads: () => lungs.reduce((n, l) => n + (l.mesh.geometry.getAttribute('position') as THREE.BufferAttribute).version, 0),
};
(window as unknown as { lungdeform: typeof api }).lungdeform = api;

api.ready = (async () => {
  resize();
  await loadModel();
  bindUI();
  setPreset(presetNames()[0]);
  setOrientation('model');
  setOverlay('none');
  if (manualClock) state.playing = false;
  syncUI();
  statusEl.textContent = loadedText();
  setupXR(renderer, $('xr'), root!, scene, BACKGROUND);
  renderer.setAnimationLoop(frame);
  return api.info();
})();
api.ready.catch(showError);
