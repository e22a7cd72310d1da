// WebXR: offer immersive AR / VR sessions where the browser supports them (the paper's setting is
// AR on a head-worn display). The patient is placed 0.6 m in front of the viewer's starting pose.
import * as THREE from 'three';

export async function setupXR(renderer: THREE.WebGLRenderer, host: HTMLElement, patient: THREE.Object3D,
                              scene: THREE.Scene, background: THREE.Color): Promise<void> {
  const xr = (navigator as Navigator & { xr?: XRSystem }).xr;
  if (!xr) {
    host.textContent = 'WebXR: not available in this browser';
    return;
  }
  const modes: XRSessionMode[] = ['immersive-ar', 'immersive-vr'];
  const supported = await Promise.all(modes.map((m) => xr.isSessionSupported(m).catch(() => false)));
  if (!supported.some(Boolean)) {
    host.textContent = 'WebXR: no immersive session supported here';
    return;
  }
  renderer.xr.enabled = true;
  renderer.xr.setReferenceSpaceType('local');
  const home = patient.position.clone();
  modes.forEach((mode, i) => {
    if (!supported[i]) return;
    const button = document.createElement('button');
    button.type = 'button';
    button.textContent = mode === 'immersive-ar' ? 'Enter AR' : 'Enter VR';
    button.onclick = async () => {
      const session = await xr.requestSession(mode, { optionalFeatures: ['local-floor'] });
      await renderer.xr.setSession(session);
      patient.position.set(0, 0, -0.6);
      if (mode === 'immersive-ar') scene.background = null;
      session.addEventListener('end', () => {
        patient.position.copy(home);
        scene.background = background;
      });
    };
    host.appendChild(button);
  });
}
