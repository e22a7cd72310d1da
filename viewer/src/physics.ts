// Pure functions behind the viewer's deformation (no three.js, no DOM): they run in node tests.
// They mirror lungdeform.force.force_weights and the exact volume cubic of lungdeform.export.
// Frames: every vector is LPS (x -> patient left, y -> posterior, z -> head), lengths in mm,
// volumes in mL (cubic coefficients in mm^3).

export type Vec3 = [number, number, number];

/** Per-lung metadata written by lungdeform.export into mesh.extras.lungdeform. */
export interface LungMeta {
  lung: string;
  side: 'left' | 'right';
  n_vertices: number;
  targets: string[];
  calibration_ml: number;
  unit_ml: number;
  share: number;
  volume_ee_ml: number;
  gravity: Vec3;
  basis_factor: number;
  tidal_volume_poly_mm3: [number, number, number, number];
  basis_volume_tensors_mm3: { a0: number; a1: number[]; a2: number[][]; a3: number[][][] };
  lung_frame: { axes: number[][]; lower: Vec3; upper: Vec3 };
  constants: number[];
  stiffness_range: [number, number];
  orientations: Record<string, { gravity: Vec3; force_weights: number[]; basis_weights: number[] }>;
}

/**
 * A marker written by lungdeform.markers.marker_anchors (asset extras.lungdeform.markers, glb schema 2):
 * at the weight lambda of its lung's target 0 ('tidal') it is at position_mm + lambda * tidal_mm
 * (LPS mm; the lung's interior field, not its nearest vertices).
 */
export interface Marker {
  label: string;
  position_mm: Vec3;
  lung: string;
  inside: boolean;
  distance_mm: number;
  tidal_mm: Vec3;
  landmark_corrected?: boolean;
}

const isVec3 = (v: unknown): v is Vec3 =>
  Array.isArray(v) && v.length === 3 && v.every((x) => typeof x === 'number' && Number.isFinite(x));

/** True for a marker this viewer can move (schema 2: a finite tidal_mm); schema-1 markers lack it. */
export function isMovable(m: Partial<Marker>): m is Marker {
  return isVec3(m.position_mm) && isVec3(m.tidal_mm) && typeof m.lung === 'string';
}

/**
 * The markers of one lung, packed once into flat buffers (LPS mm): positions(lambda) writes
 * p + lambda * w for every marker into a buffer allocated here, three multiply-adds per marker and
 * no allocation per frame.
 */
export class MarkerMotion {
  readonly count: number;
  readonly base: Float64Array;
  readonly tidal: Float64Array;
  readonly out: Float64Array;

  constructor(markers: Marker[]) {
    this.count = markers.length;
    this.base = new Float64Array(3 * markers.length);
    this.tidal = new Float64Array(3 * markers.length);
    this.out = new Float64Array(3 * markers.length);
    markers.forEach((m, i) => {
      if (!isMovable(m)) throw new Error(`marker ${JSON.stringify((m as Partial<Marker>).label)}: needs finite position_mm and tidal_mm (glb schema 2)`);
      for (let c = 0; c < 3; c++) { this.base[3 * i + c] = m.position_mm[c]; this.tidal[3 * i + c] = m.tidal_mm[c]; }
    });
    this.out.set(this.base);
  }

  /** Positions (3 per marker, LPS mm) at tidal weight lambda, in this.out (returned). */
  positions(lambda: number): Float64Array {
    const { base, tidal, out } = this;
    for (let i = 0; i < out.length; i++) out[i] = base[i] + lambda * tidal[i];
    return out;
  }
}

export const GRAVITY: Record<string, Vec3> = {
  supine: [0, 1, 0],
  prone: [0, -1, 0],
  upright: [0, 0, -1],
  'left-decubitus': [1, 0, 0],
  'right-decubitus': [-1, 0, 0],
};

export function normalize(g: Vec3): Vec3 {
  const n = Math.hypot(g[0], g[1], g[2]);
  if (!(n > 0) || !Number.isFinite(n)) throw new Error(`gravity must be a non-zero finite vector, got ${g}`);
  return [g[0] / n, g[1] / n, g[2] / n];
}

/** Weights on the fields (1, x^, y^, z^) giving the normalised height against gravity (force.height_weights). */
export function heightWeights(frame: LungMeta['lung_frame'], gravity: Vec3): number[] {
  const g = normalize(gravity);
  const a = [0, 1, 2].map((r) => {
    const gr = frame.axes[r][0] * g[0] + frame.axes[r][1] * g[1] + frame.axes[r][2] * g[2];
    return -gr * (frame.upper[r] - frame.lower[r]);
  });
  const lo = a.reduce((s, v) => s + Math.min(v, 0), 0);
  const hi = a.reduce((s, v) => s + Math.max(v, 0), 0);
  if (!(hi - lo > 0)) return [0, 0, 0, 0];
  return [-lo / (hi - lo), a[0] / (hi - lo), a[1] / (hi - lo), a[2] / (hi - lo)];
}

/** w (4): f = c7 x^ + c8 h^(gravity) + c9 z^ on the fields (1, x^, y^, z^) (force.force_weights). */
export function forceWeights(meta: LungMeta, gravity: Vec3): number[] {
  const c = meta.constants;
  const [c7, c8, c9] = [c[6], c[7], c[8]];
  const h = heightWeights(meta.lung_frame, gravity);
  return [c8 * h[0], c7 + c8 * h[1], c8 * h[2], c9 + c8 * h[3]];
}

/** Cubic coefficients (c1, c2, c3), mm^3, of the volume change for basis weights lambda * w. */
export function basisCubic(meta: LungMeta, w: number[]): [number, number, number] {
  const t = meta.basis_volume_tensors_mm3;
  let c1 = 0, c2 = 0, c3 = 0;
  for (let i = 0; i < 4; i++) {
    c1 += t.a1[i] * w[i];
    for (let j = 0; j < 4; j++) {
      c2 += t.a2[i][j] * w[i] * w[j];
      for (let k = 0; k < 4; k++) c3 += t.a3[i][j][k] * w[i] * w[j] * w[k];
    }
  }
  return [c1, c2, c3];
}

/**
 * lambda with c1 l + c2 l^2 + c3 l^3 = target (mm^3): the root nearest 0 on target's side,
 * by Newton from the linear guess (the cubic is close to linear over a breath). Constant cost.
 */
export function cubicRoot(c: [number, number, number], target: number): number {
  const [c1, c2, c3] = c;
  if (target === 0) return 0;
  if (!(c1 > 0)) throw new Error('the displacement does not grow the lung (dV/dlambda <= 0)');
  let l = target / c1;
  for (let it = 0; it < 30; it++) {
    const f = c1 * l + c2 * l * l + c3 * l * l * l - target;
    const d = c1 + 2 * c2 * l + 3 * c3 * l * l;
    if (!(d > 0)) break;
    const step = f / d;
    l -= step;
    if (Math.abs(step) <= 1e-12 * Math.max(1, Math.abs(l))) break;
  }
  return l;
}

/** The five morph weights of one lung for a volume change dvMl (mL, this lung) and gravity. */
export class LungWeights {
  readonly meta: LungMeta;
  private cubic: [number, number, number];
  private w: number[];
  native: boolean;

  private tidalCubic: [number, number, number];

  constructor(meta: LungMeta) {
    this.meta = meta;
    this.native = true;
    this.w = [0, 0, 0, 0];
    const p = meta.tidal_volume_poly_mm3;
    this.tidalCubic = [p[1], p[2], p[3]];
    this.cubic = this.tidalCubic;
  }

  /**
   * 'model' = the model's own displacement (target 0); otherwise re-orient with targets 1-4.
   * Returns false (and the lung stays at end-exhale) when that gravity's displacement does not grow
   * the lung to first order (dV/dlambda <= 0): no volume can then be reached.
   */
  setGravity(gravity: Vec3 | 'model'): boolean {
    if (gravity === 'model') {
      this.native = true;
      this.cubic = this.tidalCubic;
      this.w = [0, 0, 0, 0];
    } else {
      this.native = false;
      this.w = forceWeights(this.meta, gravity);
      this.cubic = basisCubic(this.meta, this.w);
    }
    this.valid = this.cubic[0] > 0;
    return this.valid;
  }

  valid = true;

  /** Force weights on the 4 fields for the current gravity (the model's own when native). */
  fieldWeights(): number[] {
    return this.native ? forceWeights(this.meta, this.meta.gravity) : this.w.slice();
  }

  /** Writes the 5 weights into out (exact volume; gain scales the displacement for display only). */
  weights(dvMl: number, gain: number, out: number[]): number[] {
    const l = this.valid ? cubicRoot(this.cubic, dvMl * 1000) * gain : 0;
    if (this.native) {
      out[0] = l; out[1] = 0; out[2] = 0; out[3] = 0; out[4] = 0;
    } else {
      out[0] = 0;
      for (let k = 0; k < 4; k++) out[k + 1] = l * this.w[k];
    }
    return out;
  }

  /**
   * The weight of target 0 for dvMl (mL, this lung) under the model's own gravity, times gain: the
   * markers' lambda. Equals weights()[0] when native; re-oriented (targets 1-4) it is the
   * tidal-vector approximation (markers move as under the model's gravity at the same volume), and
   * 0 while this gravity reaches no volume (the lung is then held at end-exhale too).
   */
  tidalWeight(dvMl: number, gain: number): number {
    if (!this.valid) return 0;
    return cubicRoot(this.tidalCubic, dvMl * 1000) * gain;
  }
}

/** Enclosed volume (mm^3) of a triangle mesh: positions (3n) and indices (3m), about its centroid. */
export function meshVolume(pos: ArrayLike<number>, index: ArrayLike<number>): number {
  let cx = 0, cy = 0, cz = 0;
  const n = pos.length / 3;
  for (let i = 0; i < n; i++) { cx += pos[3 * i]; cy += pos[3 * i + 1]; cz += pos[3 * i + 2]; }
  cx /= n; cy /= n; cz /= n;
  let v = 0;
  for (let f = 0; f < index.length; f += 3) {
    const a = 3 * index[f], b = 3 * index[f + 1], c = 3 * index[f + 2];
    const ax = pos[a] - cx, ay = pos[a + 1] - cy, az = pos[a + 2] - cz;
    const bx = pos[b] - cx, by = pos[b + 1] - cy, bz = pos[b + 2] - cz;
    const qx = pos[c] - cx, qy = pos[c + 1] - cy, qz = pos[c + 2] - cz;
    v += ax * (by * qz - bz * qy) + ay * (bz * qx - bx * qz) + az * (bx * qy - by * qx);
  }
  return v / 6;
}
