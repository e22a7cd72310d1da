// Colour overlays: relative stiffness, or the elastostatic force for the current gravity
// (F = sum_k w_k F_k over the 4-field force basis stored per vertex as _force_basis).
// Computed once per change of overlay or orientation, never per frame.
import * as THREE from 'three';

// viridis, 5 stops
const STOPS: [number, number, number][] = [
  [0.267, 0.005, 0.329], [0.231, 0.322, 0.545], [0.129, 0.569, 0.549], [0.369, 0.788, 0.384], [0.993, 0.906, 0.144],
];

export function colourMap(x: number, out: THREE.Color): THREE.Color {
  const f = Math.min(Math.max(x, 0), 1) * (STOPS.length - 1);
  const i = Math.min(Math.floor(f), STOPS.length - 2), u = f - i;
  const a = STOPS[i], b = STOPS[i + 1];
  return out.setRGB(a[0] + u * (b[0] - a[0]), a[1] + u * (b[1] - a[1]), a[2] + u * (b[2] - a[2]), THREE.SRGBColorSpace);
}

export function legendGradient(): string {
  return `linear-gradient(to right, ${STOPS.map((s) => `rgb(${s.map((c) => Math.round(255 * c)).join(',')})`).join(', ')})`;
}

/** Per-vertex scalar for an overlay kind, or null for plain tissue colour. */
export function overlayValues(geom: THREE.BufferGeometry, kind: string, fieldWeights: number[]): Float32Array | null {
  if (kind === 'stiffness') {
    const a = geom.getAttribute('_stiffness');
    return a ? Float32Array.from(a.array as ArrayLike<number>) : null;
  }
  if (kind === 'force') {
    const a = geom.getAttribute('_force_basis');
    if (!a) return null;
    const src = a.array as ArrayLike<number>;
    const out = new Float32Array(a.count);
    for (let i = 0; i < a.count; i++) {
      out[i] = fieldWeights[0] * src[4 * i] + fieldWeights[1] * src[4 * i + 1] + fieldWeights[2] * src[4 * i + 2] + fieldWeights[3] * src[4 * i + 3];
    }
    return out;
  }
  return null;
}

/**
 * Colour one lung mesh. Returns the value range seen (merged with `range`); with `apply`, writes
 * vertex colours using `range` (so both lungs share one scale).
 */
export function colourise(mesh: THREE.Mesh, kind: string, fieldWeights: number[],
                          range: [number, number] | null, apply = false): [number, number] | null {
  const mat = mesh.material as THREE.MeshStandardMaterial;
  const v = overlayValues(mesh.geometry, kind, fieldWeights);
  if (!v) {
    mat.vertexColors = false;
    mat.needsUpdate = true;
    return range;
  }
  let lo = range ? range[0] : Infinity, hi = range ? range[1] : -Infinity;
  if (!apply) {
    for (const x of v) { lo = Math.min(lo, x); hi = Math.max(hi, x); }
    return [lo, hi];
  }
  const colours = new Float32Array(3 * v.length);
  const c = new THREE.Color();
  const flat = !(hi - lo > 1e-9 * Math.max(Math.abs(hi), Math.abs(lo), 1e-30)); // uniform field: mid colour
  const span = flat ? 1 : hi - lo;
  for (let i = 0; i < v.length; i++) {
    colourMap(flat ? 0.5 : (v[i] - lo) / span, c);
    colours[3 * i] = c.r; colours[3 * i + 1] = c.g; colours[3 * i + 2] = c.b;
  }
  mesh.geometry.setAttribute('color', new THREE.BufferAttribute(colours, 3));
  mat.vertexColors = true;
  mat.color.set(0xffffff);
  mat.needsUpdate = true;
  return [lo, hi];
}
