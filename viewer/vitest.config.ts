import { defineConfig } from 'vitest/config';

// Node tests of the viewer's logic and of the exported .glb through three.js's GLTFLoader.
export default defineConfig({
  test: { include: ['tests/**/*.test.ts'], environment: 'node', testTimeout: 60000 },
});
