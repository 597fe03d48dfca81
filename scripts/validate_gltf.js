#!/usr/bin/env node
// Validate a .glb/.gltf with the Khronos glTF validator (npm gltf-validator,
// installed into .tools/ by scripts/test.sh).
// Usage: node scripts/validate_gltf.js FILE [--json]
// Prints a one-line summary (or the full JSON report with --json) and exits
// 0 with no errors, 1 with errors, 2 when the file could not be validated.
'use strict';
const fs = require('fs');
const path = require('path');

function loadValidator() {
  const local = path.join(__dirname, '..', '.tools', 'node_modules', 'gltf-validator');
  try {
    return require(local);
  } catch (e) {
    return require('gltf-validator');  // NODE_PATH or a global install
  }
}

const args = process.argv.slice(2);
const file = args.find((a) => !a.startsWith('--'));
if (!file) {
  console.error('usage: node scripts/validate_gltf.js FILE [--json]');
  process.exit(2);
}
const validator = loadValidator();
let bytes;
try {
  bytes = new Uint8Array(fs.readFileSync(file));
} catch (e) {
  console.error(`${file}: cannot read: ${e.message}`);
  process.exit(2);
}
validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: 0,  // no limit
  externalResourceFunction: (uri) => new Promise((resolve, reject) => {
    fs.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)),
      (err, data) => (err ? reject(err.toString()) : resolve(new Uint8Array(data))));
  }),
}).then((report) => {
  const i = report.issues;
  if (args.includes('--json')) {
    console.log(JSON.stringify(report, null, 2));
  } else {
    console.log(`${file}: ${i.numErrors} errors, ${i.numWarnings} warnings, ` +
                `${i.numInfos} infos, ${i.numHints} hints (validator ${report.validatorVersion})`);
    for (const m of i.messages) {
      if (m.severity <= 1) console.log(`  ${m.severity === 0 ? 'ERROR' : 'WARN'} ${m.code} ${m.pointer || ''}: ${m.message}`);
    }
  }
  process.exit(i.numErrors === 0 ? 0 : 1);
}, (err) => {
  console.error(`${file}: could not be validated: ${err}`);
  process.exit(2);
});
