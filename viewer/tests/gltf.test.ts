// The exported .glb through three.js's own GLTFLoader and AnimationMixer, against numbers computed
// by lungdeform in Python. Needs LUNGDEFORM_GLB (a .glb) and LUNGDEFORM_EXPECT (a JSON file written by
// tests/test_export.py); skipped without them.
import { readFileSync } from 'node:fs';
import { describe, expect, it } from 'vitest';
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { LungWeights, MarkerMotion, meshVolume, type LungMeta, type Marker } from '../src/physics';

const glbPath = process.env.LUNGDEFORM_GLB;
const expectPath = process.env.LUNGDEFORM_EXPECT;

interface Expect {
  times: number[];
  lungs: Record<string, { weights: number[]; volume_ml: number[]; orientations: Record<string, number[]> }>;
  // per marker (in the extras' order): positions (LPS mm) at each time, from lungdeform track's maths
  markers: { label: string; lung: string; positions: number[][] }[];
}

async function load() {
  const buf = readFileSync(glbPath!);
  const ab = buf.buffer.slice(buf.byteOffset, buf.byteOffset + buf.byteLength);
  return new Promise<{ scene: THREE.Group; animations: THREE.AnimationClip[]; userData: Record<string, unknown> }>(
    (resolve, reject) => new GLTFLoader().parse(ab, '', resolve as never, reject));
}

function morphed(mesh: THREE.Mesh, w: number[]): Float32Array {
  const base = mesh.geometry.getAttribute('position').array as Float32Array;
  const out = Float32Array.from(base);
  const targets = mesh.geometry.morphAttributes.position ?? [];
  targets.forEach((t, k) => {
    const a = t.array as Float32Array;
    if (w[k] !== 0) for (let i = 0; i < out.length; i++) out[i] += w[k] * a[i];
  });
  return out;
}

describe.skipIf(!glbPath || !expectPath)('exported glb in three.js', () => {
  it('loads lungs with 5 named morph targets and the custom attributes', async () => {
    const gltf = await load();
    const meshes: THREE.Mesh[] = [];
    gltf.scene.traverse((o) => { if ((o as THREE.Mesh).isMesh) meshes.push(o as THREE.Mesh); });
    expect(meshes.map((m) => m.name).sort()).toEqual(['left', 'right']);
    for (const m of meshes) {
      expect(m.geometry.morphAttributes.position?.length).toBe(5);
      expect(m.geometry.morphTargetsRelative).toBe(true);
      expect(Object.keys(m.morphTargetDictionary!)).toEqual(['tidal', 'basis_1', 'basis_x', 'basis_y', 'basis_z']);
      expect(m.geometry.getAttribute('_stiffness').itemSize).toBe(1);
      expect(m.geometry.getAttribute('_force_basis').itemSize).toBe(4);
      expect(m.geometry.getAttribute('normal').count).toBe(m.geometry.getAttribute('position').count);
    }
    expect((gltf.userData.lungdeform as { schema: string }).schema).toBe('lungdeform.glb');
  });

  it('animation weights and the morphed volumes follow the breathing curve', async () => {
    const gltf = await load();
    const ex = JSON.parse(readFileSync(expectPath!, 'utf8')) as Expect;
    const mixer = new THREE.AnimationMixer(gltf.scene);
    mixer.clipAction(gltf.animations[0]).play();
    for (let i = 0; i < ex.times.length; i++) {
      mixer.setTime(ex.times[i]);
      for (const [name, e] of Object.entries(ex.lungs)) {
        const mesh = gltf.scene.getObjectByName(name) as THREE.Mesh;
        const w = mesh.morphTargetInfluences!;
        expect(w[0]).toBeCloseTo(e.weights[i], 5);
        expect(w.slice(1).every((x) => x === 0)).toBe(true);
        // truth: the enclosed volume of the morphed float32 mesh is V_EE + share * dV(t)
        const vol = meshVolume(morphed(mesh, [...w]), mesh.geometry.index!.array) / 1000;
        expect(Math.abs(vol - e.volume_ml[i])).toBeLessThan(1e-4 * e.volume_ml[i]);
      }
    }
  });

  it('the TypeScript orientation maths reproduces Python for every named gravity', async () => {
    const gltf = await load();
    const ex = JSON.parse(readFileSync(expectPath!, 'utf8')) as Expect;
    for (const [name, e] of Object.entries(ex.lungs)) {
      const mesh = gltf.scene.getObjectByName(name) as THREE.Mesh;
      const meta = mesh.userData.lungdeform as LungMeta;
      const lw = new LungWeights(meta);
      const out = [0, 0, 0, 0, 0];
      for (const [orient, expected] of Object.entries(e.orientations)) {
        lw.setGravity(meta.orientations[orient].gravity);
        lw.weights(meta.calibration_ml, 1, out);
        for (let k = 0; k < 4; k++) expect(out[k + 1]).toBeCloseTo(expected[k], 6);
        // truth: the re-oriented float32 mesh gains exactly calibration_ml
        const vol = meshVolume(morphed(mesh, out), mesh.geometry.index!.array) / 1000;
        expect(Math.abs(vol - meta.volume_ee_ml - meta.calibration_ml)).toBeLessThan(2e-3 * meta.calibration_ml);
      }
      // the model's own gravity through the basis reproduces target 0 (built, not fitted, models)
      lw.setGravity(meta.gravity);
      lw.weights(meta.calibration_ml, 1, out);
      const viaBasis = morphed(mesh, out);
      lw.setGravity('model');
      lw.weights(meta.calibration_ml, 1, out);
      const viaTidal = morphed(mesh, out);
      let worst = 0;
      for (let i = 0; i < viaBasis.length; i++) worst = Math.max(worst, Math.abs(viaBasis[i] - viaTidal[i]));
      expect(worst).toBeLessThan(1e-2); // mm
    }
  });
  it('markers follow the interior field at the animated tidal weight', async () => {
    const gltf = await load();
    const ex = JSON.parse(readFileSync(expectPath!, 'utf8')) as Expect;
    const extras = gltf.userData.lungdeform as { schema_version: number; markers: Marker[] };
    expect(extras.schema_version).toBe(2);
    expect(extras.markers.map((m) => m.label)).toEqual(ex.markers.map((m) => m.label));
    expect(ex.markers.length).toBeGreaterThan(0);
    const mixer = new THREE.AnimationMixer(gltf.scene);
    mixer.clipAction(gltf.animations[0]).play();
    const motions = new Map(extras.markers.map((m, j) => [j, new MarkerMotion([m])]));
    let moved = 0;
    for (let i = 0; i < ex.times.length; i++) {
      mixer.setTime(ex.times[i]);
      extras.markers.forEach((m, j) => {
        const mesh = gltf.scene.getObjectByName(m.lung) as THREE.Mesh;
        // what the viewer does: position + (weight of target 0) * tidal_mm
        const x = motions.get(j)!.positions(mesh.morphTargetInfluences![0]);
        const want = ex.markers[j].positions[i];
        // truth: lungdeform.trajectory (LungModel.interior at the exact per-lung scale) in Python;
        // the animation's weights are float32 keys, so agreement is to ~1e-6 of the motion
        for (let c = 0; c < 3; c++) expect(Math.abs(x[c] - want[c])).toBeLessThan(1e-4);
        moved = Math.max(moved, Math.hypot(x[0] - m.position_mm[0], x[1] - m.position_mm[1], x[2] - m.position_mm[2]));
      });
    }
    expect(moved).toBeGreaterThan(1); // mm: the check is not on a marker that stands still
  });
});
