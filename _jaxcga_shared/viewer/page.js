// The jaxcga viewer page: reads the embedded config and data blocks, builds the three.js scene and exposes its
// state as window.jaxcgaViewer (documented in _jaxcga_shared/viewer/__init__.py).
'use strict';
(async function main() {
  const state = window.jaxcgaViewer;
  const fail = window.jaxcgaFail;
  try {
    const started = performance.now();
    const THREE = window.THREE;
    if (!THREE || !THREE.WebGLRenderer) throw new Error('three.js did not load');
    const config = JSON.parse(document.getElementById('jaxcga-config').textContent);
    document.getElementById('title').textContent = config.title;
    const sequenceFps = config.sequenceFps;

    function decodeBase64(text) {
      if (Uint8Array.fromBase64) return Uint8Array.fromBase64(text);
      const binary = atob(text);
      const bytes = new Uint8Array(binary.length);
      for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
      return bytes;
    }

    function block(index, expected, what) {
      const element = document.getElementById('jaxcga-block-' + index);
      if (!element) throw new Error(`${what}: data block ${index} is missing from the page`);
      let bytes;
      try {
        bytes = decodeBase64(element.textContent.trim());
      } catch (error) {
        throw new Error(`${what}: data block ${index} is not valid base64 (${error.message})`);
      }
      element.remove();  // its text is as large as the data: keep only the decoded bytes
      if (expected !== null && bytes.length !== expected) {
        throw new Error(`${what}: data block ${index} holds ${bytes.length} bytes, expected ${expected}`);
      }
      return bytes;
    }

    function rendererName() {
      const gl = document.createElement('canvas').getContext('webgl2');
      if (!gl) return 'none';  // three.js reports the missing context when it asks for one
      const info = gl.getExtension('WEBGL_debug_renderer_info');
      const name = String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
      const lose = gl.getExtension('WEBGL_lose_context');
      if (lose) lose.loseContext();
      return name;
    }

    // the scene
    const container = document.getElementById('view');
    // multisampling is nearly free on a GPU but costs a software renderer (SwiftShader, llvmpipe) over half its
    // frame rate: ask for it only from a hardware one
    state.renderer = rendererName();
    state.antialias = !/swiftshader|llvmpipe|softpipe|software/i.test(state.renderer);
    const renderer = new THREE.WebGLRenderer({ antialias: state.antialias, preserveDrawingBuffer: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    container.appendChild(renderer.domElement);
    const scene = new THREE.Scene();
    scene.background = new THREE.Color(0xf2f2f0);
    scene.add(new THREE.HemisphereLight(0xffffff, 0x8d8d8d, 2.0));
    const sun = new THREE.DirectionalLight(0xffffff, 2.0);
    scene.add(sun);
    const camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1000);
    scene.add(camera);
    camera.add(sun);
    sun.position.set(0.5, 1, 1);
    const controls = new THREE.OrbitControls(camera, renderer.domElement);

    function resize() {
      const w = container.clientWidth || 640;
      const h = container.clientHeight || 480;
      renderer.setSize(w, h);
      camera.aspect = w / h;
      camera.updateProjectionMatrix();
    }
    window.addEventListener('resize', resize);
    resize();

    const palette = [0xc8a27a, 0x7aa2c8, 0x9bc87a, 0xc87a9b, 0xc8c27a, 0x7ac8c0];

    // a mesh sequence: segments of frames sharing one triangle list; positions rewritten at each time
    class Sequence {
      constructor(desc, index) {
        this.desc = desc;
        this.kindName = 'sequence';
        this.center = desc.center;
        this.scale = desc.half.map((h) => h / desc.quantum);
        // groups (pieces of a cut body): a colour per vertex, by its group
        const grouped = desc.segments.some((seg) => seg.groups !== undefined);
        this.material = new THREE.MeshStandardMaterial({
          color: grouped ? 0xffffff : palette[index % palette.length], vertexColors: grouped, flatShading: true,
          side: THREE.DoubleSide, roughness: 0.7, metalness: 0.0,
        });
        let start = 0;
        this.segments = desc.segments.map((seg, k) => {
          const what = `${desc.name} (segment ${k})`;
          const indexBytes = block(seg.indices, null, what);
          if (indexBytes.length % 12) throw new Error(`${what}: triangle block of ${indexBytes.length} bytes`);
          const indices = new Uint32Array(indexBytes.buffer, indexBytes.byteOffset, indexBytes.length / 4);
          for (let i = 0; i < indices.length; i++) {
            if (indices[i] >= seg.vertices) throw new Error(`${what}: triangle index ${indices[i]} out of range`);
          }
          let frames;
          if (Array.isArray(seg.positions)) {
            frames = seg.positions.map((f) => Float32Array.from(f));
            if (frames.length !== seg.frames || frames.some((f) => f.length !== 3 * seg.vertices)) {
              throw new Error(`${what}: frames do not match ${seg.frames} x ${seg.vertices} vertices`);
            }
          } else {
            const bytes = block(seg.positions, seg.frames * seg.vertices * 6, what);
            frames = new Int16Array(bytes.buffer, bytes.byteOffset, bytes.length / 2);
          }
          const geometry = new THREE.BufferGeometry();
          const position = new THREE.BufferAttribute(new Float32Array(3 * seg.vertices), 3);
          position.setUsage(THREE.DynamicDrawUsage);
          geometry.setAttribute('position', position);
          geometry.setIndex(new THREE.BufferAttribute(indices, 1));
          if (grouped) {
            const colour = new Float32Array(3 * seg.vertices);
            let groups = null;
            if (seg.groups !== undefined) {
              const bytes = block(seg.groups, 4 * seg.vertices, what);
              groups = new Uint32Array(bytes.buffer, bytes.byteOffset, seg.vertices);
            }
            const c = new THREE.Color();
            for (let i = 0; i < seg.vertices; i++) {
              c.setHex(palette[((groups ? groups[i] : 0) + index) % palette.length]);
              colour[3 * i] = c.r; colour[3 * i + 1] = c.g; colour[3 * i + 2] = c.b;
            }
            geometry.setAttribute('color', new THREE.BufferAttribute(colour, 3));
          }
          const segment = { start, count: seg.frames, vertices: seg.vertices, frames, geometry };
          start += seg.frames;
          return segment;
        });
        this.frameCount = start;
        this.duration = (this.frameCount - 1) / sequenceFps;
        this.object = new THREE.Mesh(this.segments[0].geometry, this.material);
        this.object.frustumCulled = false;
        this.frame = -1;
        this.setTime(0);
      }

      framePositions(segment, k) {  // frame k of a segment as a Float32Array view or an Int16Array view
        const n3 = 3 * segment.vertices;
        return Array.isArray(segment.frames) ? segment.frames[k] : segment.frames.subarray(k * n3, (k + 1) * n3);
      }

      setTime(t) {
        const f = Math.min(Math.max(t * sequenceFps, 0), this.frameCount - 1);
        const k0 = Math.floor(f);
        const segment = this.segments.find((s) => k0 < s.start + s.count);
        const local = k0 - segment.start;
        // linear between two frames of one segment; a change of triangles is shown at its frame
        const a = local + 1 < segment.count ? f - k0 : 0;
        const p0 = this.framePositions(segment, local);
        const p1 = a > 0 ? this.framePositions(segment, local + 1) : p0;
        const out = segment.geometry.attributes.position.array;
        const quantized = !Array.isArray(segment.frames);
        const c = quantized ? this.center : [0, 0, 0];
        const s = quantized ? this.scale : [1, 1, 1];
        const b = 1 - a;
        for (let i = 0; i < out.length; i += 3) {
          out[i] = c[0] + s[0] * (b * p0[i] + a * p1[i]);
          out[i + 1] = c[1] + s[1] * (b * p0[i + 1] + a * p1[i + 1]);
          out[i + 2] = c[2] + s[2] * (b * p0[i + 2] + a * p1[i + 2]);
        }
        segment.geometry.attributes.position.needsUpdate = true;
        if (this.object && this.object.geometry !== segment.geometry) this.object.geometry = segment.geometry;
        this.frame = k0;
      }

      meshes() { return [this.object]; }
    }

    // a glTF as three.js loads it: its clips played by an AnimationMixer, skinning on the GPU
    class Gltf {
      async load(desc) {
        this.desc = desc;
        const bytes = block(desc.data, null, desc.name);
        const loader = new THREE.GLTFLoader();
        let gltf;
        try {
          gltf = await loader.parseAsync(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.length), '');
        } catch (error) {
          throw new Error(`${desc.name}: three.js cannot load this glTF (${error.message || error})`);
        }
        this.object = gltf.scene;
        this.clips = gltf.animations;
        this.mixer = new THREE.AnimationMixer(gltf.scene);
        const order = (o) => {
          const a = gltf.parser.associations.get(o) || {};
          return [a.meshes ?? 1e9, a.primitives ?? 0];
        };
        const found = [];
        gltf.scene.traverse((o) => { if (o.isMesh) found.push(o); });
        this.meshList = found
          .map((o, k) => [order(o), k, o])
          .sort((x, y) => x[0][0] - y[0][0] || x[0][1] - y[0][1] || x[1] - y[1])
          .map((x) => x[2]);
        if (!this.meshList.length) throw new Error(`${desc.name}: three.js found no mesh in this glTF`);
        this.skinned = this.meshList.some((m) => m.isSkinnedMesh);
        this.kindName = this.skinned ? 'skinned' : 'static';
        this.action = null;
        return this;
      }

      setClip(name) {
        this.mixer.stopAllAction();
        const clip = this.clips.find((c) => c.name === name);
        this.action = clip ? this.mixer.clipAction(clip) : null;
        if (this.action) this.action.play();
        this.duration = clip ? clip.duration : 0;
      }

      setTime(t) {
        if (this.action) {
          // a zero step evaluates the clip at exactly action.time (no wrap, no end-of-clip handling)
          this.action.time = Math.min(t, this.duration);
          this.mixer.update(0);
        }
      }

      meshes() { return this.meshList; }
    }

    // build every input
    const items = [];
    for (let k = 0; k < config.items.length; k++) {
      const desc = config.items[k];
      items.push(desc.kind === 'gltf' ? await new Gltf().load(desc) : new Sequence(desc, k));
    }
    state.decodeMs = performance.now() - started;
    const sequences = items.filter((it) => it instanceof Sequence);
    const gltfs = items.filter((it) => it instanceof Gltf);

    // the box an input sweeps: a sequence's over all frames; a glTF's over its rest pose and samples of its clips
    function sweptBox(it) {
      if (it instanceof Sequence) {
        const c = new THREE.Vector3(...it.center);
        const h = new THREE.Vector3(...it.desc.half);
        return new THREE.Box3(c.clone().sub(h), c.clone().add(h));
      }
      const box = new THREE.Box3();
      for (const name of [undefined, ...it.clips.map((c) => c.name)]) {
        it.setClip(name);
        for (let s = 0; s <= (name === undefined ? 0 : 16); s++) {
          it.setTime((it.duration * s) / 16);
          it.object.updateMatrixWorld(true);
          box.union(new THREE.Box3().setFromObject(it.object, true));
        }
      }
      it.setClip(undefined);
      return box;
    }

    // side by side along x, each by the box it sweeps, so that no two overlap while they move
    const slots = [];
    const boxes = items.map(sweptBox);
    const gap = 0.1 * Math.max(...boxes.map((b) => {
      const size = b.getSize(new THREE.Vector3());
      return Math.max(size.x, size.y, size.z);
    }));
    let cursor = 0;
    items.forEach((it, k) => {
      const slot = new THREE.Group();
      slot.add(it.object);
      scene.add(slot);
      slot.position.x = cursor - boxes[k].min.x;
      cursor += boxes[k].max.x - boxes[k].min.x + gap;
      slots.push(slot);
    });
    scene.updateMatrixWorld(true);

    // each input's name under it, kept there as the view turns (an HTML label over the canvas)
    const labels = items.map((it) => {
      const label = document.createElement('div');
      label.className = 'label';
      label.textContent = it.desc.name;
      document.getElementById('view').appendChild(label);
      return label;
    });
    function placeLabels() {
      const canvas = renderer.domElement;
      state.labels = items.map((it, k) => {
        const box = boxes[k].clone().translate(slots[k].position);
        const foot = new THREE.Vector3((box.min.x + box.max.x) / 2, box.min.y, (box.min.z + box.max.z) / 2);
        foot.project(camera);
        const x = ((foot.x + 1) / 2) * canvas.clientWidth;
        const y = ((1 - foot.y) / 2) * canvas.clientHeight;
        labels[k].style.left = `${x}px`;
        labels[k].style.top = `${y}px`;
        return { name: it.desc.name, x, y };
      });
    }

    // clips: by name across the glTFs; sequences only: one clip "frames"
    const clipNames = [];
    for (const g of gltfs) for (const c of g.clips) if (!clipNames.includes(c.name)) clipNames.push(c.name);
    const sequenceDuration = Math.max(0, ...sequences.map((s) => s.duration));
    state.clips = clipNames.length
      ? clipNames.map((name) => ({
        name,
        duration: Math.max(...gltfs.map((g) => (g.clips.find((c) => c.name === name) || { duration: 0 }).duration)),
      }))
      : (sequenceDuration > 0 ? [{ name: 'frames', duration: sequenceDuration }] : []);

    // skeletons and joint weights
    const skeletonHelpers = gltfs.filter((g) => g.skinned).map((g) => {
      const helper = new THREE.SkeletonHelper(g.object);
      helper.visible = false;
      scene.add(helper);
      return helper;
    });
    const skinnedMeshes = gltfs.flatMap((g) => g.meshList.filter((m) => m.isSkinnedMesh));
    const jointNames = [];
    for (const m of skinnedMeshes) for (const b of m.skeleton.bones) if (!jointNames.includes(b.name)) jointNames.push(b.name);
    const weightMaterials = new Map();

    function jointIndex(mesh, joint) {
      if (typeof joint === 'number') return joint;
      return mesh.skeleton.bones.findIndex((b) => b.name === joint);
    }

    function weightColours(mesh, j) {
      const index = mesh.geometry.attributes.skinIndex;
      const weight = mesh.geometry.attributes.skinWeight;
      const colour = new Float32Array(3 * index.count);
      let touched = 0;
      for (let i = 0; i < index.count; i++) {
        let w = 0;
        for (let c = 0; c < 4; c++) if (index.getComponent(i, c) === j) w += weight.getComponent(i, c);
        if (w > 0) touched++;
        colour[3 * i] = 0.15 + 0.8 * w;
        colour[3 * i + 1] = 0.25 + 0.1 * w;
        colour[3 * i + 2] = 0.85 - 0.75 * w;
      }
      return [colour, touched];
    }

    // state and controls
    let clipIndex = -1;
    const sequenceColours = [];
    Object.assign(state, {
      clip: -1, duration: 0, time: 0, frame: -1, playing: false, speed: 1, loop: true, sequenceFps,
      interpolation: 'linear', fps: 0, rendered: 0, frameChanges: 0, updateMs: 0, joint: null,
    });

    function refreshClock() {
      document.getElementById('clock').textContent =
        `${state.time.toFixed(2)} / ${state.duration.toFixed(2)} s` + (sequences.length ? `, frame ${state.frame}` : '');
      const scrub = document.getElementById('scrub');
      scrub.max = String(state.duration || 1);
      scrub.value = String(state.time);
      document.getElementById('play').textContent = state.playing ? 'Pause' : 'Play';
    }

    function applyTime(t) {
      const start = performance.now();
      state.time = t;
      // an input shorter than the span played holds its end until all start again together
      for (const it of items) it.setTime(Math.min(t, it.duration || 0));
      const frame = sequences.length ? sequences[0].frame : -1;
      if (frame !== state.frame) state.frameChanges++;
      state.frame = frame;
      scene.updateMatrixWorld(true);
      state.updateMs = performance.now() - start;
      refreshClock();
    }

    state.setTime = (t) => { applyTime(Math.min(Math.max(Number(t), 0), state.duration)); render(); return state.time; };
    state.play = () => { if (state.time >= state.duration && !state.loop) applyTime(0); state.playing = true; refreshClock(); };
    state.pause = () => { state.playing = false; refreshClock(); };
    state.setSpeed = (s) => { state.speed = Number(s); document.getElementById('speed').value = String(s); };
    state.setLoop = (b) => { state.loop = !!b; document.getElementById('loop').checked = state.loop; };
    state.setClip = (i) => {
      if (!(i >= 0 && i < Math.max(state.clips.length, 1))) throw new Error(`setClip: no clip ${i}`);
      clipIndex = state.clips.length ? i : -1;
      const name = clipNames[i];
      for (const g of gltfs) g.setClip(name);
      state.clip = clipIndex;
      state.duration = Math.max(sequenceDuration, ...gltfs.map((g) => g.duration || 0));
      document.getElementById('clip').value = String(i);
      applyTime(0);
      return state.clip;
    };
    state.setWireframe = (b) => {
      const on = !!b;
      scene.traverse((o) => {
        if (o.isMesh) for (const m of [].concat(o.material)) m.wireframe = on;
      });
      for (const m of weightMaterials.values()) m.wireframe = on;
      document.getElementById('wireframe').checked = on;
      render();
    };
    state.showSkeleton = (b) => {
      for (const h of skeletonHelpers) h.visible = !!b;
      document.getElementById('skeleton').checked = !!b;
      render();
    };
    state.showWeights = (joint) => {
      let touched = 0;
      for (const mesh of skinnedMeshes) {
        if (!mesh.userData.material) mesh.userData.material = mesh.material;
        const j = joint === null || joint === undefined ? -1 : jointIndex(mesh, joint);
        if (j < 0) { mesh.material = mesh.userData.material; continue; }
        const [colour, count] = weightColours(mesh, j);
        touched += count;
        mesh.geometry.setAttribute('color', new THREE.BufferAttribute(colour, 3));
        if (!weightMaterials.has(mesh)) {
          weightMaterials.set(mesh, new THREE.MeshStandardMaterial({ vertexColors: true, roughness: 0.8 }));
        }
        mesh.material = weightMaterials.get(mesh);
        mesh.material.wireframe = document.getElementById('wireframe').checked;
      }
      if (joint !== null && joint !== undefined && !skinnedMeshes.some((m) => jointIndex(m, joint) >= 0)) {
        throw new Error(`showWeights: no skin has the joint ${JSON.stringify(joint)}`);
      }
      state.joint = joint === undefined ? null : joint;
      const first = skinnedMeshes.length ? skinnedMeshes[0].skeleton.bones[joint] : undefined;
      document.getElementById('joint').value = typeof joint === 'string' ? joint : (first ? first.name : '');
      render();
      return touched;
    };

    let home = null;
    state.resetView = () => {
      const box = new THREE.Box3();
      boxes.forEach((b, k) => box.union(b.clone().translate(slots[k].position)));
      const radius = Math.max(box.getSize(new THREE.Vector3()).length() / 2, 1e-6);
      // the corners of each input's own box (not of the box around all: its empty corners would push the camera
      // back), centred in the view's own axes; then the nearest distance along the view direction at which every
      // corner is in the picture, with a margin: a row of models side by side fills the width
      const toward = new THREE.Vector3(0.35, 0.3, 1).normalize();
      const right = new THREE.Vector3(0, 1, 0).cross(toward).normalize();
      const up = toward.clone().cross(right);
      const corners = [];
      boxes.forEach((b, k) => {
        const moved = b.clone().translate(slots[k].position);
        for (const x of [moved.min.x, moved.max.x]) for (const y of [moved.min.y, moved.max.y]) {
          for (const z of [moved.min.z, moved.max.z]) corners.push(new THREE.Vector3(x, y, z));
        }
      });
      const middle = (axis) => {
        const values = corners.map((c) => c.dot(axis));
        return (Math.min(...values) + Math.max(...values)) / 2;
      };
      const center = right.clone().multiplyScalar(middle(right))
        .add(up.clone().multiplyScalar(middle(up))).add(toward.clone().multiplyScalar(middle(toward)));
      const tanV = Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
      const tanH = tanV * camera.aspect;
      let distance = 1e-6;
      for (const point of corners) {
        const corner = point.clone().sub(center);
        const depth = corner.dot(toward);
        distance = Math.max(distance, depth + Math.abs(corner.dot(right)) / tanH, depth + Math.abs(corner.dot(up)) / tanV);
      }
      // in perspective the near side of the row looks larger than the far side: centre and close in on the
      // corners as projected (a few rounds: each moves the centre to the middle of the picture's extents and
      // scales the distance so that they just fit; never past the nearest corner)
      const nearest = Math.max(...corners.map((c) => c.clone().sub(center).dot(toward)));
      for (let round = 0; round < 8; round++) {
        camera.position.copy(center).add(toward.clone().multiplyScalar(distance));
        camera.lookAt(center);
        camera.updateMatrixWorld();
        const lo = [Infinity, Infinity];
        const hi = [-Infinity, -Infinity];
        for (const point of corners) {
          const q = point.clone().project(camera);
          lo[0] = Math.min(lo[0], q.x); hi[0] = Math.max(hi[0], q.x);
          lo[1] = Math.min(lo[1], q.y); hi[1] = Math.max(hi[1], q.y);
        }
        center.add(right.clone().multiplyScalar(((lo[0] + hi[0]) / 2) * distance * tanH))
          .add(up.clone().multiplyScalar(((lo[1] + hi[1]) / 2) * distance * tanV));
        const extent = Math.max((hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2);
        distance = Math.max(distance * extent, nearest * 1.05 + 1e-6);
      }
      distance *= 1.1;
      if (!home) home = { center, distance, radius };
      camera.near = Math.max(home.distance - home.radius, home.distance / 100) / 10;
      camera.far = (home.distance + home.radius) * 10;
      camera.position.copy(home.center).add(toward.multiplyScalar(home.distance));
      camera.updateProjectionMatrix();
      controls.target.copy(home.center);
      controls.update();
      render();
    };

    state.vertexPositions = (i) => {
      const it = items[i];
      if (!it) throw new Error(`vertexPositions: no mesh ${i}`);
      scene.updateMatrixWorld(true);
      const undo = slots[i].matrixWorld.clone().invert();
      const v = new THREE.Vector3();
      const out = [];
      for (const mesh of it.meshes()) {
        const toInput = undo.clone().multiply(mesh.matrixWorld);
        const count = mesh.geometry.attributes.position.count;
        for (let k = 0; k < count; k++) {
          mesh.getVertexPosition(k, v);  // skinned: the bone transform applied as the shader does
          v.applyMatrix4(toInput);
          out.push(v.x, v.y, v.z);
        }
      }
      return out;
    };
    state.boundingBox = () => {
      const box = new THREE.Box3();
      for (const slot of slots) box.expandByObject(slot, true);
      return { min: box.min.toArray(), max: box.max.toArray() };
    };

    function describeMeshes() {
      state.meshes = items.map((it, k) => {
        const list = it.meshes();
        const vertexCount = list.reduce((n, m) => n + m.geometry.attributes.position.count, 0);
        const triangleCount = list.reduce(
          (n, m) => n + (m.geometry.index ? m.geometry.index.count : m.geometry.attributes.position.count) / 3, 0);
        const kind = it instanceof Sequence ? (it.frameCount > 1 ? 'sequence' : 'static') : it.kindName;
        return { name: it.desc.name, kind, vertexCount, triangleCount, source: it.desc.source,
          offset: slots[k].position.toArray() };
      });
    }

    // the controls' elements
    const clipSelect = document.getElementById('clip');
    state.clips.forEach((c, k) => clipSelect.add(new Option(`${c.name} (${c.duration.toFixed(2)} s)`, String(k))));
    const jointSelect = document.getElementById('joint');
    for (const name of jointNames) jointSelect.add(new Option(name, name));
    if (!jointNames.length) jointSelect.disabled = true;
    if (!skeletonHelpers.length) document.getElementById('skeleton').disabled = true;
    const guard = (fn) => (event) => { try { fn(event); } catch (error) { fail(error); } };
    document.getElementById('play').addEventListener('click', guard(() => (state.playing ? state.pause() : state.play())));
    document.getElementById('scrub').addEventListener('input', guard((e) => state.setTime(Number(e.target.value))));
    document.getElementById('speed').addEventListener('change', guard((e) => state.setSpeed(Number(e.target.value))));
    document.getElementById('loop').addEventListener('change', guard((e) => state.setLoop(e.target.checked)));
    clipSelect.addEventListener('change', guard((e) => state.setClip(Number(e.target.value))));
    document.getElementById('reset').addEventListener('click', guard(() => state.resetView()));
    document.getElementById('wireframe').addEventListener('change', guard((e) => state.setWireframe(e.target.checked)));
    document.getElementById('skeleton').addEventListener('change', guard((e) => state.showSkeleton(e.target.checked)));
    jointSelect.addEventListener('change', guard((e) => state.showWeights(e.target.value || null)));

    function render() {
      renderer.render(scene, camera);
      placeLabels();
      state.rendered++;
    }

    // the loop: advance the time while playing, render, count rendered frames per second
    const stamps = [];
    let last = performance.now();
    function tick(now) {
      try {
        const dt = Math.min((now - last) / 1000, 0.25);
        last = now;
        if (state.playing && state.duration > 0) {
          let t = state.time + dt * state.speed;
          if (t > state.duration) {
            if (state.loop) t %= state.duration;
            else { t = state.duration; state.playing = false; }
          }
          applyTime(t);
        }
        render();
        stamps.push(now);
        while (stamps.length && stamps[0] < now - 1000) stamps.shift();
        state.fps = stamps.length;
      } catch (error) {
        fail(error);
        return;
      }
      requestAnimationFrame(tick);
    }

    state.setClip(Math.min(config.clip, Math.max(state.clips.length - 1, 0)));
    describeMeshes();
    state.resetView();
    if (config.joint !== null) state.showWeights(config.joint);
    state.loadMs = performance.now();
    state.ready = true;
    state.playing = state.duration > 0;
    refreshClock();
    requestAnimationFrame(tick);
  } catch (error) {
    fail(error);
  }
})();
