// Runs the Khronos glTF validator (npm's gltf-validator, installed by
// `npm ci` from validator/package-lock.json into a folder of the build) on
// one .glb or .gltf and prints its report as JSON.
//   node validate_gltf.js NODE_MODULES_DIR FILE
// Exits 0 when the report has no error and no warning, 1 when it has any
// (infos and hints are printed, not counted), 2 when it cannot run.
'use strict';
const fs = require('fs');
const path = require('path');

if (process.argv.length !== 4) {
  console.error('usage: node validate_gltf.js NODE_MODULES_DIR FILE');
  process.exit(2);
}
const [modules, file] = process.argv.slice(2);
let validator;
try {
  validator = require(path.join(path.resolve(modules), 'gltf-validator'));
} catch (e) {
  console.error(`cannot load gltf-validator from ${modules}: ${e.message}`);
  process.exit(2);
}

const directory = path.dirname(path.resolve(file));
validator
  .validateBytes(new Uint8Array(fs.readFileSync(file)), {
    uri: path.basename(file),
    maxIssues: 0,  // every issue, not the first 100
    // External buffers and images, for a .gltf beside its files.
    externalResourceFunction: (uri) =>
      new Promise((resolve, reject) => {
        fs.readFile(path.join(directory, decodeURIComponent(uri)), (error, data) =>
          error ? reject(error.toString()) : resolve(new Uint8Array(data)));
      }),
  })
  .then((report) => {
    console.log(JSON.stringify(report, null, 2));
    const { numErrors, numWarnings } = report.issues;
    console.error(`${file}: ${numErrors} errors, ${numWarnings} warnings, ${report.issues.numInfos} infos, ` +
                  `${report.issues.numHints} hints`);
    process.exit(numErrors === 0 && numWarnings === 0 ? 0 : 1);
  })
  .catch((error) => {
    console.error(`validating ${file} failed: ${error}`);
    process.exit(2);
  });
