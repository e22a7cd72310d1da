// Run the Khronos glTF validator on one .glb and print its report as JSON on stdout.
// Usage: node scripts/validate-glb.mjs FILE.glb   (exit 0 when the report has no errors, 1 otherwise)
import { readFile } from 'node:fs/promises';
import validator from 'gltf-validator';

const file = process.argv[2];
if (!file) {
  console.error('usage: node scripts/validate-glb.mjs FILE.glb');
  process.exit(2);
}
const bytes = new Uint8Array(await readFile(file));
const report = await validator.validateBytes(bytes, {
  uri: file,
  maxIssues: 100,
  externalResourceFunction: () => Promise.reject(new Error('no external resources expected')),
});
process.stdout.write(JSON.stringify(report, null, 1));
process.exit(report.issues.numErrors === 0 ? 0 : 1);
