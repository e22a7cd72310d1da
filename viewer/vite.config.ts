import { defineConfig } from 'vite';
import { fileURLToPath } from 'node:url';

// The built bundle ships inside the Python package (lungdeform/data/viewer) and is served by
// `lungdeform view`. Relative base: the server may be mounted anywhere.
export default defineConfig({
  base: './',
  build: {
    outDir: fileURLToPath(new URL('../src/lungdeform/data/viewer', import.meta.url)),
    emptyOutDir: true,
    assetsDir: 'assets',
    sourcemap: false,
    chunkSizeWarningLimit: 1200,
    target: 'es2022',
    // stable names (the server sends no-store, so no cache-busting hashes are needed; diffs stay small)
    rollupOptions: {
      output: { entryFileNames: 'assets/viewer.js', chunkFileNames: 'assets/[name].js', assetFileNames: 'assets/[name][extname]' },
    },
  },
});
