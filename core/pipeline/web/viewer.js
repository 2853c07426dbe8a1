// The interactive 3D view of report.html: the region surfaces of the simplified mesh, one
// checkbox per region. esbuild bundles this file with the parts of three.js it uses into one
// script that core/pipeline/report.cc writes inline into the page, so the page works offline
// (no network, no file beside it).
//
// The page holds (report.cc writes them):
//   <div id="decima-3d">                      where the canvas goes
//   <script id="decima-surfaces-meta">        JSON: bounds_mm [6], regions [{label, name,
//                                             colour, vertices, triangles, shown}]
//   <script id="decima-surfaces-data">        base64 of zlib-deflated binary: per region, its
//                                             vertices as 3 little-endian uint16 each
//                                             (quantized on bounds_mm), then its triangles'
//                                             3 vertex indices each, every index as the
//                                             zigzag LEB128 varint of its difference from the
//                                             previous index of the region
// When the first frame is drawn, the container gets data-state="ready" and the console one line
// "decima-3d: ready; regions N; shown M; canvas X,Y,W,H; right A, left B, up C, down D; scale
// S mm" (the canvas's page rectangle in CSS pixels, the orientation letters on its edges and the
// scale bar's length), which the browser test (tests/core/pipeline/report_test.cc) reads; an
// error sets data-state="error: ..." and is logged with console.error.
//
// Orientation letters and the mm scale follow the camera as the 2D pictures' do
// (core/render/annotate.cc): each edge gets the patient direction(s) it faces, and the bar is
// measured at the depth of the point the view turns about (a perspective view has no single
// scale).
import {
  AmbientLight,
  Box3,
  BufferAttribute,
  BufferGeometry,
  Color,
  DirectionalLight,
  DoubleSide,
  Mesh,
  MeshLambertMaterial,
  PerspectiveCamera,
  Scene,
  Vector3,
  WebGLRenderer,
} from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

function fail(box, e) {
  const message = String((e && e.message) || e);
  box.dataset.state = 'error: ' + message;
  console.error('decima-3d: ' + message);
  const p = document.createElement('p');
  p.className = 'warn';
  p.textContent = '3D view unavailable: ' + message;
  box.replaceChildren(p);
}

// The letters of a patient direction d (LPS): the dominant axis, then the second one if its
// component is at least a third of |d|; the rule of OrientationLetters in core/render/annotate.cc.
function orientationLetters(d) {
  const pos = ['L', 'P', 'S'];
  const neg = ['R', 'A', 'I'];
  const c = [d.x, d.y, d.z];
  const n = Math.hypot(c[0], c[1], c[2]);
  if (!(n > 0)) return '';
  const order = [0, 1, 2].sort((a, b) => Math.abs(c[b]) - Math.abs(c[a]));
  const letter = (i) => (c[i] > 0 ? pos[i] : neg[i]);
  return letter(order[0]) + (Math.abs(c[order[1]]) >= n / 3 ? letter(order[1]) : '');
}

// The longest round length that spans at most a quarter of the width (ScaleBarMm's steps).
function scaleBarMm(pixelsPerMm, width) {
  for (const mm of [500, 200, 100, 50, 20, 10, 5, 2, 1]) {
    if (mm * pixelsPerMm <= width / 4) return mm;
  }
  return 1;
}

// Letters on the four edges and a scale bar, as HTML over the canvas; update() after each move.
function overlay(stage, width, height) {
  const text = 'position:absolute;color:#ebebeb;font:bold 14px monospace;' +
    'text-shadow:0 0 2px #000,0 0 2px #000;pointer-events:none;';
  const make = (css) => {
    const e = document.createElement('span');
    e.style.cssText = text + css;
    stage.append(e);
    return e;
  };
  const edges = {
    right: make('right:6px;top:50%;transform:translateY(-50%);'),
    left: make('left:6px;top:50%;transform:translateY(-50%);'),
    up: make('top:6px;left:50%;transform:translateX(-50%);'),
    down: make('bottom:6px;left:50%;transform:translateX(-50%);'),
  };
  const bar = document.createElement('div');
  bar.style.cssText = 'position:absolute;left:10px;bottom:30px;height:3px;background:#ebebeb;' +
    'box-shadow:0 0 2px #000;pointer-events:none;';
  stage.append(bar);
  const barLabel = make('left:10px;bottom:10px;');
  barLabel.title = 'at the depth of the point the view turns about';
  const state = { letters: {}, mm: 0 };
  return {
    state,
    update(camera, target) {
      const right = new Vector3(1, 0, 0).applyQuaternion(camera.quaternion);
      const up = new Vector3(0, 1, 0).applyQuaternion(camera.quaternion);
      const dirs = { right, left: right.clone().negate(), up, down: up.clone().negate() };
      for (const [edge, d] of Object.entries(dirs)) {
        state.letters[edge] = orientationLetters(d);
        edges[edge].textContent = state.letters[edge];
      }
      const depth = camera.position.distanceTo(target);
      const visibleMm = 2 * depth * Math.tan((camera.fov * Math.PI) / 360);
      const pixelsPerMm = height / visibleMm;
      state.mm = scaleBarMm(pixelsPerMm, width);
      bar.style.width = Math.round(state.mm * pixelsPerMm) + 'px';
      barLabel.textContent = state.mm + ' mm';
    },
  };
}

async function inflate(base64) {
  const bytes = Uint8Array.from(atob(base64), (c) => c.charCodeAt(0));
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('deflate'));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

function geometries(meta, data) {
  const [x0, y0, z0, x1, y1, z1] = meta.bounds_mm;
  const scale = [(x1 - x0) / 65535, (y1 - y0) / 65535, (z1 - z0) / 65535];
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  let at = 0;
  const out = meta.regions.map((r) => {
    const positions = new Float32Array(3 * r.vertices);
    for (let i = 0; i < 3 * r.vertices; ++i, at += 2) {
      positions[i] = [x0, y0, z0][i % 3] + scale[i % 3] * view.getUint16(at, true);
    }
    const index = new Uint32Array(3 * r.triangles);
    let previous = 0;
    for (let i = 0; i < 3 * r.triangles; ++i) {
      let v = 0;
      let shift = 0;
      let byte;
      do {
        if (at >= data.byteLength) throw new Error('surface data shorter than its description');
        byte = data[at++];
        v += (byte & 0x7f) * 2 ** shift;
        shift += 7;
      } while (byte & 0x80);
      previous += v % 2 ? -(v + 1) / 2 : v / 2;
      if (previous < 0 || previous >= r.vertices) throw new Error('vertex index out of range');
      index[i] = previous;
    }
    const g = new BufferGeometry();
    g.setAttribute('position', new BufferAttribute(positions, 3));
    g.setIndex(new BufferAttribute(index, 1));
    g.computeVertexNormals();
    return g;
  });
  if (at !== data.byteLength) throw new Error('surface data longer than its description');
  return out;
}

async function main(box) {
  const meta = JSON.parse(document.getElementById('decima-surfaces-meta').textContent);
  const data = await inflate(document.getElementById('decima-surfaces-data').textContent.trim());
  const width = Math.min(box.clientWidth || 720, 900);
  const height = Math.round(width * 0.75);
  const renderer = new WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setSize(width, height);
  const scene = new Scene();
  scene.background = new Color(0x18181c);
  scene.add(new AmbientLight(0xffffff, 0.9));
  // Patient frame (LPS mm): x to the patient's left, y posterior, z superior. The camera starts
  // in front of the face (anterior), head up, as the anterior render of the report, framing the
  // regions shown at first (the hidden space around the patient is a much larger box).
  const camera = new PerspectiveCamera(35, width / height, 1, 10);
  camera.up.set(0, 0, 1);
  const light = new DirectionalLight(0xffffff, 1.6);
  camera.add(light); // the light follows the eye, so every side turned to it is lit
  scene.add(camera);
  const controls = new OrbitControls(camera, renderer.domElement);

  const list = document.createElement('div');
  list.className = 'toggles';
  const geos = geometries(meta, data);
  const meshes = meta.regions.map((r, i) => {
    const mesh = new Mesh(
      geos[i],
      new MeshLambertMaterial({ color: new Color(r.colour), side: DoubleSide }),
    );
    mesh.visible = !!r.shown;
    scene.add(mesh);
    const label = document.createElement('label');
    const tick = document.createElement('input');
    tick.type = 'checkbox';
    tick.checked = mesh.visible;
    tick.dataset.label = r.label;
    tick.addEventListener('change', () => {
      mesh.visible = tick.checked;
      draw();
    });
    const swatch = document.createElement('span');
    swatch.className = 'swatch';
    swatch.style.background = r.colour;
    label.append(tick, ' ', swatch, ' ', r.name);
    list.append(label);
    return mesh;
  });
  const frame = new Box3();
  for (const m of meshes) if (m.visible) frame.expandByObject(m);
  if (frame.isEmpty()) for (const m of meshes) frame.expandByObject(m);
  const centre = frame.getCenter(new Vector3());
  const extent = frame.getSize(new Vector3());
  const size = Math.max(extent.x, extent.y, extent.z) || 1;
  camera.near = size / 100;
  camera.far = size * 20;
  camera.position.set(centre.x, centre.y - 2 * size, centre.z);
  camera.updateProjectionMatrix();
  light.position.set(size, size, 0);
  controls.target.copy(centre);
  controls.update();

  const canvas = renderer.domElement;
  const stage = document.createElement('div');
  stage.style.cssText = 'position:relative;display:inline-block;max-width:100%;';
  stage.append(canvas);
  const marks = overlay(stage, width, height);
  box.replaceChildren(stage, list);
  function draw() {
    renderer.render(scene, camera);
    marks.update(camera, controls.target);
  }
  controls.addEventListener('change', draw);
  draw();
  const rect = canvas.getBoundingClientRect();
  const at = [rect.left + window.scrollX, rect.top + window.scrollY, rect.width, rect.height];
  box.dataset.state = 'ready';
  const shown = meta.regions.filter((r) => r.shown).length;
  const l = marks.state.letters;
  console.info(`decima-3d: ready; regions ${meta.regions.length}; shown ${shown}; canvas ` +
    at.map(Math.round).join(',') +
    `; right ${l.right}, left ${l.left}, up ${l.up}, down ${l.down}; scale ${marks.state.mm} mm`);
}

const box = document.getElementById('decima-3d');
if (box) {
  window.addEventListener('error', (e) => fail(box, e.error || e.message));
  main(box).catch((e) => fail(box, e));
}
