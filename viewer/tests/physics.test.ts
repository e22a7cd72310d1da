// Unit tests of the viewer's pure logic (no model needed).
import { describe, expect, it } from 'vitest';
import { cubicRoot, heightWeights, isMovable, LungWeights, MarkerMotion, meshVolume, normalize, type LungMeta, type Marker } from '../src/physics';
import { builtinCurves, countCycles, sampledCurve, volumeAt } from '../src/curves';

describe('cubicRoot', () => {
  it('inverts the cubic on both sides of zero', () => {
    // truth: evaluate the cubic at the returned root
    const c: [number, number, number] = [2000, -30, 0.4];
    for (const target of [-500, -1, 1, 250e3 / 1000, 5000]) {
      const l = cubicRoot(c, target);
      expect(c[0] * l + c[1] * l * l + c[2] * l ** 3).toBeCloseTo(target, 6);
    }
    expect(cubicRoot(c, 0)).toBe(0);
  });
  it('refuses a displacement that does not grow the volume', () => {
    expect(() => cubicRoot([-1, 0, 0], 10)).toThrow();
  });
});

describe('heightWeights', () => {
  it('gives height 0 at the lowest box corner and 1 at the highest', () => {
    // identity axes, box 0..100 in each: gravity -z -> height = z^ exactly
    const frame = { axes: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], lower: [0, 0, 0] as [number, number, number], upper: [100, 100, 100] as [number, number, number] };
    const up = heightWeights(frame, [0, 0, -1]);
    [0, 0, 0, 1].forEach((x, i) => expect(up[i]).toBeCloseTo(x, 12));
    const w = heightWeights(frame, normalize([1, 1, 0]));
    // h = 1 - (x^ + y^)/2: at (0,0) 1, at (1,1) 0
    expect(w[0]).toBeCloseTo(1);
    expect(w[1]).toBeCloseTo(-0.5);
    expect(w[2]).toBeCloseTo(-0.5);
  });
});

describe('meshVolume', () => {
  it('is the volume of a unit cube (12 outward triangles)', () => {
    const p = [0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 0, 0, 1, 1, 0, 1, 1, 1, 1, 0, 1, 1];
    const f = [0, 2, 1, 0, 3, 2, 4, 5, 6, 4, 6, 7, 0, 1, 5, 0, 5, 4, 1, 2, 6, 1, 6, 5, 2, 3, 7, 2, 7, 6, 3, 0, 4, 3, 4, 7];
    expect(meshVolume(p, f)).toBeCloseTo(1, 12);
  });
});

describe('curves', () => {
  it('built-in shapes start at end-exhale, reach end-inhale and are periodic', () => {
    for (const c of builtinCurves()) {
      expect(c.shape(0)).toBeCloseTo(0, 9);
      let peak = 0;
      for (let i = 0; i <= 1000; i++) peak = Math.max(peak, c.shape(i / 1000));
      expect(peak).toBeCloseTo(1, 4);
      expect(c.shape(0.999999)).toBeCloseTo(0, 3);
      // tidal and rate scale the curve: volume at t and at t + one period agree
      const loop = 60 / 10;
      expect(volumeAt(c, 1.3, 800, 10)).toBeCloseTo(volumeAt(c, 1.3 + loop, 800, 10), 6);
      expect(Math.max(...Array.from({ length: 601 }, (_, i) => volumeAt(c, (i / 600) * loop, 800, 10)))).toBeCloseTo(800, 0);
    }
  });
  it('sampled curves interpolate their samples and count their breaths', () => {
    const t = Array.from({ length: 401 }, (_, i) => i * 0.05); // 20 s
    const v = t.map((x) => 250 * (1 - Math.cos((2 * Math.PI * x) / 5))); // 4 breaths of 5 s
    expect(countCycles(v)).toBe(4);
    const c = sampledCurve('s', 's', t, v, 'test');
    expect(c.rateBpm).toBeCloseTo(12, 9);
    expect(c.tidalMl).toBeCloseTo(500, 6);
    expect(volumeAt(c, 2.5, c.tidalMl, c.rateBpm)).toBeCloseTo(500, 6);
    expect(volumeAt(c, 1.0, c.tidalMl, c.rateBpm)).toBeCloseTo(250 * (1 - Math.cos((2 * Math.PI) / 5)), 1);
  });
});

describe('markers', () => {
  const markers: Marker[] = [
    { label: 'a', position_mm: [90, 10, -20], lung: 'left', inside: true, distance_mm: 50, tidal_mm: [3.5, -13.75, -1.5] },
    { label: 'b', position_mm: [100, 0, 40], lung: 'left', inside: true, distance_mm: 30, tidal_mm: [0.25, -8, 2] },
  ];
  it('move by position + lambda * tidal_mm, into one buffer allocated once', () => {
    // truth: the formula of the glb extras (schema 2), evaluated by hand
    const motion = new MarkerMotion(markers);
    const first = motion.positions(0);
    expect(Array.from(first)).toEqual([90, 10, -20, 100, 0, 40]);
    const x = motion.positions(0.6);
    expect(x).toBe(first); // the same buffer: nothing allocated per frame
    const want = [90 + 0.6 * 3.5, 10 - 0.6 * 13.75, -20 - 0.6 * 1.5, 100 + 0.6 * 0.25, -0.6 * 8, 40 + 0.6 * 2];
    want.forEach((v, i) => expect(x[i]).toBeCloseTo(v, 12));
  });
  it('refuses markers of an older export (anchor vertices, no tidal_mm)', () => {
    const old = { label: 'old', position_mm: [90, 0, 0], lung: 'left', vertices: [1, 2, 3, 4], weights: [0.25, 0.25, 0.25, 0.25] };
    expect(isMovable(old as unknown as Partial<Marker>)).toBe(false);
    expect(isMovable(markers[0])).toBe(true);
    expect(isMovable({ ...markers[0], tidal_mm: [1, NaN, 0] })).toBe(false);
    expect(() => new MarkerMotion([old as unknown as Marker])).toThrow(/tidal_mm/);
  });
});

describe('LungWeights.tidalWeight', () => {
  // a synthetic lung: tidal cubic V(l) = 2000 l - 30 l^2 + 0.4 l^3 (mm^3); basis with c8 = 1 (force =
  // height) and a1 = (1000, 0, 0, 1000): upright (gravity -z, height = z^) grows it, gravity +z does not
  const meta = {
    lung: 'left', side: 'left', n_vertices: 0, targets: [], calibration_ml: 250, unit_ml: 1, share: 0.5,
    volume_ee_ml: 1000, gravity: [0, 1, 0], basis_factor: 1, tidal_volume_poly_mm3: [1e6, 2000, -30, 0.4],
    basis_volume_tensors_mm3: { a0: 1e6, a1: [1000, 0, 0, 1000], a2: [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]],
      a3: Array.from({ length: 4 }, () => Array.from({ length: 4 }, () => [0, 0, 0, 0])) },
    lung_frame: { axes: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], lower: [0, 0, 0], upper: [100, 100, 100] },
    constants: [0, 0, 0, 0, 0, 0, 0, 1, 0], stiffness_range: [1, 1], orientations: {},
  } as unknown as LungMeta;
  it('is the weight of target 0 for the volume, whatever the orientation', () => {
    const lw = new LungWeights(meta);
    const out = [0, 0, 0, 0, 0];
    lw.weights(3, 2, out); // 3 mL, display gain 2
    const l = lw.tidalWeight(3, 2);
    expect(l).toBe(out[0]); // native: the markers' lambda is target 0's weight
    // truth: the tidal cubic at l / gain gives 3 mL
    const x = l / 2;
    expect(2000 * x - 30 * x * x + 0.4 * x ** 3).toBeCloseTo(3000, 6);
    expect(lw.setGravity([0, 0, -1])).toBe(true);
    lw.weights(3, 2, out);
    expect(out[0]).toBe(0); // re-oriented: the mesh plays targets 1-4 ...
    expect(lw.tidalWeight(3, 2)).toBe(l); // ... the markers keep the tidal weight of the same volume
    expect(lw.setGravity([0, 0, 1])).toBe(false); // a gravity that grows no volume: held at end-exhale
    expect(lw.tidalWeight(3, 2)).toBe(0);
  });
});
