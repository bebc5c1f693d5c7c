// stex viewer: plays a run's tracked mesh with its per-frame texture (written by `stex view`).
// The data's layout is described in stex/viewer/write.py; positions are in three.js's camera
// convention with the input colour camera at the origin, so that camera is three.js's default
// camera and only its projection comes from the intrinsics.
import * as THREE from 'three';
import { OrbitControls } from './three/OrbitControls.js';

const params = new URLSearchParams(location.search);
const FIXED = params.get('camera') === 'input';  // the input camera's exact view, no orbit
const CACHE = 24;     // frames kept decoded (textures on the GPU)
const PREFETCH = 6;   // frames loaded ahead of the one shown
const NEAR = 0.01, FAR = 100.0;  // metres
const BACKGROUND = 48 / 255;  // the grey behind the mesh in `stex preview`

const el = (id) => document.getElementById(id);
const status = (text) => { el('status').textContent = text; };

// What a test (or a console) reads and drives: frame = position shown, shown = frames drawn so far.
const state = { ready: false, error: null, frame: -1, frameId: null, shown: 0, playing: false };
window.stexViewer = state;

function roundHalfEven(x) {  // Python's round(), which stex.camera.Intrinsics.scaled uses
  const r = Math.round(x);
  return (Math.abs(x - Math.trunc(x)) === 0.5 && r % 2 !== 0) ? r - 1 : r;
}

// The colour camera for an image `height` pixels high: stex.camera.Intrinsics.scaled (pixel
// centres kept), as `stex preview` renders its panels.
function scaledCamera(cam, height) {
  const f = height / cam.height;
  return { fx: cam.fx * f, fy: cam.fy * f, cx: (cam.cx + 0.5) * f - 0.5, cy: (cam.cy + 0.5) * f - 0.5,
           width: roundHalfEven(cam.width * f), height: roundHalfEven(cam.height * f) };
}

// OpenCV pinhole (pixel centres at integers, y down) -> clip space of a camera looking down -z
// with y up: pixel (u, v) lands on window coordinates (u + 0.5, height - v - 0.5).
function projection(c) {
  const m = new THREE.Matrix4();
  m.set(2 * c.fx / c.width, 0, 1 - 2 * (c.cx + 0.5) / c.width, 0,
        0, 2 * c.fy / c.height, 2 * (c.cy + 0.5) / c.height - 1, 0,
        0, 0, -(FAR + NEAR) / (FAR - NEAR), -2 * FAR * NEAR / (FAR - NEAR),
        0, 0, -1, 0);
  return m;
}

async function fetchOk(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r;
}

function loadImage(url) {
  const img = new Image();
  img.src = url;
  return img.decode().then(() => img, () => { throw new Error(`${url}: cannot load the image`); });
}

function imageTexture(img, nearest) {
  // row 0 of the image is v = 0 (stex texcoords), so no flip; no mipmaps and bilinear lookups
  // (nearest for label colours), no colour conversion: the bytes as stored, as stex renders them
  const t = new THREE.Texture(img);
  t.flipY = false;
  t.generateMipmaps = false;
  t.minFilter = t.magFilter = nearest ? THREE.NearestFilter : THREE.LinearFilter;
  t.wrapS = t.wrapT = THREE.ClampToEdgeWrapping;
  t.colorSpace = THREE.NoColorSpace;
  t.needsUpdate = true;
  return t;
}

async function main() {
  THREE.ColorManagement.enabled = false;
  const view = await (await fetchOk('view.json')).json();
  const frames = view.frames;
  const n = frames.length;
  el('title').textContent = `${view.scene} · ${view.source} · ${n} frames`;
  const [meshBuf, posBuf] = await Promise.all([
    fetchOk(view.mesh.file).then((r) => r.arrayBuffer()),
    fetchOk(view.positions.file).then((r) => r.arrayBuffer())]);
  const m = view.mesh;
  const vertexIndex = new Uint32Array(meshBuf, m.vertex_index.offset, m.vertex_index.count);
  const uv = new Float32Array(meshBuf, m.uv.offset, m.uv.count);
  const index = new Uint32Array(meshBuf, m.index.offset, m.index.count);
  const code = new Uint16Array(posBuf);
  const V = view.n_vertices;
  if (code.length !== n * V * 3) throw new Error(`${view.positions.file}: ${code.length} values, expected ${n * V * 3}`);
  const [o, s] = [view.positions.offset, view.positions.step];

  const geometry = new THREE.BufferGeometry();
  const position = new THREE.BufferAttribute(new Float32Array(vertexIndex.length * 3), 3);
  position.setUsage(THREE.DynamicDrawUsage);
  geometry.setAttribute('position', position);
  geometry.setAttribute('uv', new THREE.BufferAttribute(uv, 2));
  geometry.setIndex(new THREE.BufferAttribute(index, 1));
  function setPositions(k) {
    const p = position.array, base = k * V * 3;
    for (let i = 0; i < vertexIndex.length; i++) {
      const q = base + vertexIndex[i] * 3;
      p[3 * i] = o[0] + code[q] * s[0];
      p[3 * i + 1] = o[1] + code[q + 1] * s[1];
      p[3 * i + 2] = o[2] + code[q + 2] * s[2];
    }
    position.needsUpdate = true;
  }

  // unlit: the texture as it is (as `stex preview` renders it), the label colours mixed over it
  const material = new THREE.ShaderMaterial({
    uniforms: { map: { value: null }, labels: { value: null }, showLabels: { value: 0.0 } },
    vertexShader: `varying vec2 vUv;
      void main() { vUv = uv; gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0); }`,
    fragmentShader: `uniform sampler2D map; uniform sampler2D labels; uniform float showLabels; varying vec2 vUv;
      void main() {
        vec3 c = texture2D(map, vUv).rgb;
        if (showLabels > 0.5) c = mix(c, texture2D(labels, vUv).rgb, 0.65);
        gl_FragColor = vec4(c, 1.0);
      }`,
    side: THREE.DoubleSide,  // open templates show their inside, as stex's renderer does
  });
  const mesh = new THREE.Mesh(geometry, material);
  mesh.frustumCulled = false;  // positions change every frame; no bounding sphere kept
  const scene = new THREE.Scene();
  scene.add(mesh);

  // sizes: the canvas has the colour camera's aspect; `camera=input` draws at size=H exactly
  const cam = view.camera;
  let height = parseInt(params.get('size') || '360', 10);
  if (!(height >= 16 && height <= 4096)) throw new Error(`size=${params.get('size')}: give 16..4096 pixels`);
  height += height % 2;  // as `stex preview` (even panel heights)
  if (!FIXED && !params.has('size')) {
    const aspect = cam.width / cam.height;
    height = Math.max(240, Math.min(720, window.innerHeight - 130, (window.innerWidth - 40) / (2 * aspect)));
    height = Math.floor(height / 2) * 2;
  }
  const K = scaledCamera(cam, height);
  const canvas = el('view');
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);  // one canvas pixel per image pixel: the input view is compared pixel by pixel
  renderer.setSize(K.width, K.height);
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  renderer.setClearColor(new THREE.Color(BACKGROUND, BACKGROUND, BACKGROUND), 1);
  el('input').style.height = `${K.height}px`;

  const camera = new THREE.PerspectiveCamera(2 * Math.atan(K.height / (2 * K.fy)) * 180 / Math.PI,
                                             K.width / K.height, NEAR, FAR);
  camera.projectionMatrix.copy(projection(K));  // the intrinsics, principal point included
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  // orbit about the point of the optical axis at the object's depth: looking at it from the
  // origin keeps the input camera's orientation, so the first view is the input view
  const pivot = new THREE.Vector3(0, 0, view.center[2]);
  const controls = new OrbitControls(camera, canvas);
  controls.enabled = !FIXED;
  controls.target.copy(pivot);
  controls.update();
  const render = () => renderer.render(scene, camera);
  controls.addEventListener('change', render);
  el('reset').onclick = () => { camera.position.set(0, 0, 0); controls.target.copy(pivot); controls.update(); render(); };
  el('reset').disabled = FIXED;

  // frames: images decoded and uploaded on demand, the most recently used kept
  const cache = new Map();
  function load(k) {
    let p = cache.get(k);
    if (p) { cache.delete(k); cache.set(k, p); return p; }
    const f = frames[k];
    p = Promise.all([loadImage(f.texture), f.labels ? loadImage(f.labels) : null, loadImage(f.color)])
      .then(([t, l, c]) => ({ texture: imageTexture(t, false), labels: l && imageTexture(l, true), color: c.src }));
    cache.set(k, p);
    for (const [j, old] of cache) {
      if (cache.size <= CACHE) break;
      if (j === state.frame) continue;
      cache.delete(j);
      old.then((d) => { d.texture.dispose(); if (d.labels) d.labels.dispose(); }, () => {});
    }
    return p;
  }

  const slider = el('slider');
  slider.max = String(n - 1);
  let wanted = -1;
  async function show(k) {
    wanted = k;
    const d = await load(k);
    if (wanted !== k) return;  // another frame was asked for meanwhile
    setPositions(k);
    material.uniforms.map.value = d.texture;
    material.uniforms.labels.value = d.labels || d.texture;
    el('input').src = d.color;
    slider.value = String(k);
    el('frame-label').textContent = `frame ${frames[k].id} (${k + 1}/${n})`;
    render();
    state.frame = k;
    state.frameId = frames[k].id;
    state.shown += 1;
    document.body.dataset.frame = String(k);
    for (let j = 1; j <= PREFETCH && j < n; j++) load((k + j) % n).catch(() => {});
  }
  state.setFrame = (k) => show(Math.max(0, Math.min(n - 1, k | 0)));

  function setPlaying(on) {
    state.playing = on;
    el('play').textContent = on ? 'pause' : 'play';
  }
  state.play = () => setPlaying(true);
  state.pause = () => setPlaying(false);
  el('play').onclick = () => setPlaying(!state.playing);
  slider.oninput = () => { setPlaying(false); show(parseInt(slider.value, 10)); };
  const overlay = el('labels');
  overlay.disabled = !view.labels;
  overlay.onchange = () => { material.uniforms.showLabels.value = overlay.checked ? 1.0 : 0.0; render(); };
  overlay.checked = view.labels && params.get('labels') === '1';
  overlay.onchange();
  window.addEventListener('keydown', (e) => {
    if (e.target !== document.body) return;
    if (e.key === ' ') { setPlaying(!state.playing); e.preventDefault(); }
    if (e.key === 'ArrowRight' || e.key === 'ArrowLeft') {
      setPlaying(false);
      show((state.frame + (e.key === 'ArrowRight' ? 1 : n - 1)) % n);
    }
  });

  // playback at the capture's pace; a frame still loading holds the next one back
  let last = 0, busy = false;
  function tick(now) {
    requestAnimationFrame(tick);
    if (!state.playing || busy || now - last < 1000 / view.fps) return;
    busy = true;
    last = now;
    show((state.frame + 1) % n).catch(fail).finally(() => { busy = false; });
  }
  await show(Math.max(0, Math.min(n - 1, parseInt(params.get('frame') || '0', 10) || 0)));
  state.ready = true;
  status(`${view.fps.toFixed(1)} frames/s`);
  setPlaying(params.get('play') === '1');
  requestAnimationFrame(tick);
}

function fail(err) {
  state.error = String(err && err.message || err);
  status(`error: ${state.error}`);
  console.error(err);
}

main().catch(fail);
