// Check a glTF/GLB file with the tools that will open it.
//
//   node tests/gltf_validate.mjs <file.glb|file.gltf> [--no-three] [--sample=t0,t1,...]
//
// Prints one JSON object on stdout:
//   { file, validator: {version, numErrors, numWarnings, numInfos, numHints, messages[]},
//     three: {meshes: [{name, vertices, morphTargets, targetNames, morphTargetInfluences}],
//             animations: [{name, duration, tracks: [{name, times, values}]}]} }
// "validator" is the Khronos glTF Validator (npm gltf-validator); "three" is what three.js's
// GLTFLoader.parse builds from the bytes (runs in node without a DOM for files whose buffers
// are embedded and that have no images). With --sample=t0,t1,... "three.samples" holds the
// first mesh's morphTargetInfluences after an AnimationMixer plays animations[0] to each time
// (seconds): three.js's own LINEAR / CUBICSPLINE interpolation of the file.
//
// Exit codes: 0 ran (look at numErrors), 1 a tool threw, 2 bad arguments,
// 3 node_modules missing (run `npm ci` at the repository root).

import fs from 'node:fs';
import path from 'node:path';

const args = process.argv.slice(2);
const file = args.find((a) => !a.startsWith('--'));
const sampleArg = args.find((a) => a.startsWith('--sample='));
const sampleTimes = sampleArg ? sampleArg.slice('--sample='.length).split(',').map(Number) : [];
if (!file) {
  console.error('usage: node tests/gltf_validate.mjs <file.glb|file.gltf> [--no-three]');
  process.exit(2);
}

async function need(spec) {
  try {
    return await import(spec);
  } catch (e) {
    if (e && (e.code === 'ERR_MODULE_NOT_FOUND' || e.code === 'MODULE_NOT_FOUND')) {
      console.error(`cannot import ${spec}: node_modules is missing or incomplete; run \`npm ci\` at the repository root`);
      process.exit(3);
    }
    throw e;
  }
}

const validatorModule = await need('gltf-validator');
const validator = validatorModule.default ?? validatorModule;
const bytes = new Uint8Array(fs.readFileSync(file));

const report = await validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: 200,
  externalResourceFunction: (uri) =>
    new Promise((resolve, reject) => {
      fs.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)), (err, data) =>
        err ? reject(err.toString()) : resolve(new Uint8Array(data)));
    }),
});

const out = {
  file,
  validator: {
    version: report.validatorVersion,
    numErrors: report.issues.numErrors,
    numWarnings: report.issues.numWarnings,
    numInfos: report.issues.numInfos,
    numHints: report.issues.numHints,
    messages: report.issues.messages.map((m) => ({
      code: m.code, severity: m.severity, message: m.message, pointer: m.pointer,
    })),
  },
};

if (!args.includes('--no-three')) {
  await need('three');
  // three's FileLoader (used for data: URI buffers of .gltf files) fires ProgressEvent, which
  // node 20 lacks; a minimal stand-in is enough, nothing reads more than its fields.
  globalThis.ProgressEvent ??= class ProgressEvent extends Event {
    constructor(type, init = {}) { super(type); Object.assign(this, init); }
  };
  const { GLTFLoader } = await need('three/examples/jsm/loaders/GLTFLoader.js');
  const buf = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
  const gltf = await new Promise((resolve, reject) =>
    new GLTFLoader().parse(buf, path.dirname(path.resolve(file)) + '/', resolve, reject));
  const meshes = [];
  gltf.scene.traverse((o) => {
    if (o.isMesh) {
      const g = o.geometry;
      meshes.push({
        name: o.name,
        vertices: g.attributes.position.count,
        hasNormals: 'normal' in g.attributes,
        morphTargets: (g.morphAttributes.position || []).length,
        morphNormals: (g.morphAttributes.normal || []).length,
        targetNames: Object.entries(o.morphTargetDictionary || {})
          .sort((a, b) => a[1] - b[1]).map((e) => e[0]),
        morphTargetInfluences: o.morphTargetInfluences ? Array.from(o.morphTargetInfluences) : [],
      });
    }
  });
  let samples = [];
  if (sampleTimes.length && gltf.animations.length) {
    const { AnimationMixer } = await need('three');
    let first = null;
    gltf.scene.traverse((o) => { if (o.isMesh && !first) first = o; });
    const mixer = new AnimationMixer(gltf.scene);
    mixer.clipAction(gltf.animations[0]).play();
    samples = sampleTimes.map((t) => {
      mixer.setTime(t);
      return Array.from(first.morphTargetInfluences);
    });
  }
  out.three = {
    meshes,
    samples,
    animations: gltf.animations.map((a) => ({
      name: a.name,
      duration: a.duration,
      tracks: a.tracks.map((t) => ({ name: t.name, times: t.times.length, values: t.values.length })),
    })),
  };
}

console.log(JSON.stringify(out));
