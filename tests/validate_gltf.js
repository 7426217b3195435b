// The Khronos glTF validator on .glb files: prints one JSON report per file (its issues' counts and
// messages), for tests/stores/test_gltf.py. Run with NODE_PATH pointing at the folder where setup.sh
// installed the npm package gltf-validator (.venv/node/node_modules).
const fs = require("fs");
const validator = require("gltf-validator");

async function main() {
  const reports = {};
  for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {maxIssues: 100});
    reports[file] = {
      numErrors: report.issues.numErrors, numWarnings: report.issues.numWarnings,
      messages: report.issues.messages.map(m => `${["error", "warning", "info", "hint"][m.severity]} ${m.code} ${m.pointer || ""}: ${m.message}`),
      info: report.info,
    };
  }
  process.stdout.write(JSON.stringify(reports));
}

main().catch(e => { console.error(e); process.exit(1); });
