// Unit tests of the viewer's pure logic (no model needed).
import { describe, expect, it } from 'vitest';
import { cubicRoot, heightWeights, meshVolume, normalize } from '../src/physics';
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
