// The mbnt viewer: lists sequences and jobs from the API, follows running jobs' progress, and
// draws a fitted job's points, trajectories, moving bodies and loss curve on 2D canvases with a
// small perspective projection of its own (no library, no build step).
//
// What it draws comes from the API alone: the job's points at every frame time are answered by
// `POST /v1/jobs/{id}/query`, the bodies by `/objects`, the sensor poses by `/poses` and the loss
// curve by `/losses` (a running job's by its events). `window.mbntViewer` exposes what was drawn,
// for the browser test and for anyone curious in the console.
'use strict';

(() => {
  const $ = (id) => document.getElementById(id);

  const TOKEN_KEY = 'mbnt-api-token';
  // A frame shows at most this many points, and a query asks at most this many positions
  // (points x frame times): about 12 MB of JSON at the most.
  const MAX_POINTS = 20000;
  const MAX_POSITIONS = 400000;
  const MAX_TRAILS = 400;
  // Jobs whose progress streams stay open at once besides the opened one (each holds a
  // connection, and a browser allows six per server).
  const MAX_FOLLOWED = 3;
  const LIST_REFRESH_MS = 3000;
  const BACKGROUND = '#0f141c';
  // A point moving slower than this (m per time unit) is drawn as still.
  const STILL_SPEED = 0.3;
  // A point within this margin (m) of a body's box, at its own frame, is coloured as the body's.
  const BOX_MARGIN_M = 0.3;

  const exposed = {
    ready: false, jobId: null, boxes: 0, objects: 0, points: 0, times: 0, timeIndex: 0,
    lossRecords: 0, probe: null, error: null,
  };
  window.mbntViewer = exposed;

  const state = {
    token: sessionStorage.getItem(TOKEN_KEY) || '',
    jobId: null,
    jobAbort: null, // aborts the opened job's requests and progress stream
    followed: new Map(), // job id -> AbortController of its progress stream in the list
    jobs: [],
    scene: null,
    camera: null,
    loss: { records: [], live: false },
    playTimer: null,
  };

  // --- the API ---------------------------------------------------------------------------

  class ApiError extends Error {
    constructor(status, problem) {
      super(problem && problem.detail ? problem.detail : `HTTP ${status}`);
      this.status = status;
      this.problem = problem;
    }
  }

  function headers(extra) {
    const h = Object.assign({}, extra);
    if (state.token) h.Authorization = `Bearer ${state.token}`;
    return h;
  }

  async function api(path, { method = 'GET', json, signal } = {}) {
    const init = { method, headers: headers({ Accept: 'application/json' }), signal };
    if (json !== undefined) {
      init.headers['Content-Type'] = 'application/json';
      init.body = JSON.stringify(json);
    }
    const response = await fetch(path, init);
    if (!response.ok) {
      let problem = null;
      try {
        problem = await response.json();
      } catch (_) {
        // Not a problem document: the status says enough.
      }
      throw new ApiError(response.status, problem);
    }
    return response.json();
  }

  // Server-sent events read through fetch, since EventSource cannot send the token.
  async function follow(jobId, onEvent, signal) {
    const response = await fetch(`/v1/jobs/${encodeURIComponent(jobId)}/events`, {
      headers: headers({ Accept: 'text/event-stream' }), signal,
    });
    if (!response.ok) throw new ApiError(response.status, null);
    const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = '';
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      buffer += value;
      for (let end = buffer.search(/\r?\n\r?\n/); end >= 0; end = buffer.search(/\r?\n\r?\n/)) {
        const block = buffer.slice(0, end);
        buffer = buffer.slice(end).replace(/^\r?\n\r?\n/, '');
        let event = 'message';
        const data = [];
        for (const line of block.split(/\r?\n/)) {
          if (line === '' || line.startsWith(':')) continue;
          const colon = line.indexOf(':');
          const field = colon < 0 ? line : line.slice(0, colon);
          let v = colon < 0 ? '' : line.slice(colon + 1);
          if (v.startsWith(' ')) v = v.slice(1);
          if (field === 'event') event = v;
          else if (field === 'data') data.push(v);
        }
        if (data.length) onEvent(event, JSON.parse(data.join('\n')));
      }
    }
  }

  const isAbort = (e) => e && e.name === 'AbortError';

  function setStatus(text, error = false) {
    const status = $('status');
    status.textContent = text;
    status.classList.toggle('error', error);
  }

  // Reports a failed call: a 401 asks for the token; anything else is shown as the problem says.
  function report(e, what) {
    if (isAbort(e)) return;
    if (e instanceof ApiError && e.status === 401) {
      $('token-form').classList.add('needed');
      setStatus(state.token ? 'The API token was refused: enter the right one.'
        : 'This server needs an API token: enter it above.', true);
    } else {
      setStatus(`${what}: ${e.message}`, true);
    }
    exposed.error = `${what}: ${e.message}`;
  }

  // --- lists -----------------------------------------------------------------------------

  const short = (id) => id.slice(0, 8);

  function fmt(v, digits = 3) {
    if (v === null || v === undefined || !Number.isFinite(v)) return '-';
    return Math.abs(v) >= 1000 || (Math.abs(v) < 0.001 && v !== 0) ? v.toExponential(2) : v.toFixed(digits);
  }

  function progressText(job) {
    const p = job.progress || {};
    const parts = [job.status];
    if (p.iterations) parts.push(`${p.iteration}/${p.iterations} it`);
    if (p.loss) parts.push(`loss ${fmt(p.loss.total)}`);
    if (p.rigid_tracks && job.status === 'running') parts.push(`bodies ${p.rigid_tracks.clusters_done}/${p.rigid_tracks.clusters}`);
    if (p.window) parts.push(`window ${p.window.window + 1}/${p.window.windows}`);
    if (Number.isFinite(p.eta_s) && !['succeeded', 'failed', 'cancelled'].includes(job.status)) {
      parts.push(`~${Math.ceil(p.eta_s)} s left`);
    }
    if (job.error) parts.push(job.error);
    return parts.join(' · ');
  }

  function jobItem(job) {
    const li = document.createElement('li');
    li.dataset.jobId = job.id;
    li.className = `status-${job.status}`;
    if (job.id === state.jobId) li.classList.add('selected');
    const link = document.createElement('a');
    link.href = `/?job=${encodeURIComponent(job.id)}`;
    link.textContent = `${short(job.id)} ${job.method}`;
    link.addEventListener('click', (event) => {
      event.preventDefault();
      history.pushState(null, '', link.href);
      openJob(job.id);
    });
    const meta = document.createElement('div');
    meta.className = 'meta';
    meta.textContent = progressText(job);
    const bar = document.createElement('div');
    bar.className = 'bar';
    const fill = document.createElement('span');
    fill.style.width = `${Math.round(100 * Math.min(1, Math.max(0, (job.progress || {}).fraction || 0)))}%`;
    bar.appendChild(fill);
    li.append(link, meta, bar);
    return li;
  }

  function updateJobItem(job) {
    const i = state.jobs.findIndex((j) => j.id === job.id);
    if (i >= 0) state.jobs[i] = job;
    const old = document.querySelector(`#jobs li[data-job-id="${job.id}"]`);
    if (old) old.replaceWith(jobItem(job));
  }

  function renderLists(sequences, jobs) {
    const seqList = $('sequences');
    seqList.replaceChildren(...sequences.map((s) => {
      const li = document.createElement('li');
      const name = document.createElement('strong');
      name.textContent = s.name || short(s.id);
      const meta = document.createElement('div');
      meta.className = 'meta';
      const points = s.points_per_frame.reduce((a, b) => a + b, 0);
      meta.textContent = `${s.frames} frames · ${points.toLocaleString('en')} points${s.has_poses ? ' · poses' : ''}`;
      const count = jobs.filter((j) => j.sequence_id === s.id).length;
      if (count) meta.textContent += ` · ${count} job${count > 1 ? 's' : ''}`;
      li.append(name, meta);
      return li;
    }));
    if (!sequences.length) seqList.replaceChildren(Object.assign(document.createElement('li'), { textContent: 'none yet' }));
    state.jobs = jobs;
    const jobList = $('jobs');
    jobList.replaceChildren(...jobs.map(jobItem));
    if (!jobs.length) jobList.replaceChildren(Object.assign(document.createElement('li'), { textContent: 'none yet' }));
  }

  // Keeps a progress stream open for each of the newest active jobs, so their bars move live.
  function followActive() {
    const active = state.jobs.filter((j) => j.status === 'queued' || j.status === 'running')
      .filter((j) => j.id !== state.jobId).slice(0, MAX_FOLLOWED).map((j) => j.id);
    for (const [id, abort] of state.followed) {
      if (!active.includes(id)) {
        abort.abort();
        state.followed.delete(id);
      }
    }
    for (const id of active) {
      if (state.followed.has(id)) continue;
      const abort = new AbortController();
      state.followed.set(id, abort);
      follow(id, (_, job) => updateJobItem(job), abort.signal)
        .catch((e) => { if (!isAbort(e)) console.warn('progress stream', id, e.message); })
        .finally(() => { if (state.followed.get(id) === abort) state.followed.delete(id); });
    }
  }

  let listTimer = null;
  async function refreshLists() {
    clearTimeout(listTimer);
    try {
      const [sequences, jobs] = await Promise.all([api('/v1/sequences'), api('/v1/jobs')]);
      renderLists(sequences.sequences, jobs.jobs);
      followActive();
      $('token-form').classList.remove('needed');
      if (exposed.error && exposed.error.startsWith('Listing')) {
        setStatus('');
        exposed.error = null;
      }
      listTimer = setTimeout(refreshLists, LIST_REFRESH_MS);
    } catch (e) {
      report(e, 'Listing');
      // Without the token, asking again changes nothing until one is entered.
      if (!(e instanceof ApiError && e.status === 401)) listTimer = setTimeout(refreshLists, LIST_REFRESH_MS);
    }
  }

  // --- small linear algebra (row-major 4 x 4) --------------------------------------------

  const IDENTITY = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];

  function apply(m, x, y, z) {
    return [
      m[0] * x + m[1] * y + m[2] * z + m[3],
      m[4] * x + m[5] * y + m[6] * z + m[7],
      m[8] * x + m[9] * y + m[10] * z + m[11],
    ];
  }

  function compose(a, b) {
    const out = new Array(16).fill(0);
    for (let r = 0; r < 4; r++) {
      for (let c = 0; c < 4; c++) {
        for (let k = 0; k < 4; k++) out[4 * r + c] += a[4 * r + k] * b[4 * k + c];
      }
    }
    return out;
  }

  // The inverse of a rigid transform: rotation transposed, translation rotated back.
  function rigidInverse(m) {
    const t = [m[3], m[7], m[11]];
    const out = [m[0], m[4], m[8], 0, m[1], m[5], m[9], 0, m[2], m[6], m[10], 0, 0, 0, 0, 1];
    for (let r = 0; r < 3; r++) out[4 * r + 3] = -(out[4 * r] * t[0] + out[4 * r + 1] * t[1] + out[4 * r + 2] * t[2]);
    return out;
  }

  function quantile(values, q) {
    if (!values.length) return 0;
    const sorted = Float64Array.from(values).sort();
    return sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
  }

  // --- a job -----------------------------------------------------------------------------

  function showJobView(show) {
    $('job-view').hidden = !show;
    $('welcome').hidden = show;
  }

  function stopPlaying() {
    clearInterval(state.playTimer);
    state.playTimer = null;
    $('play').textContent = 'Play';
  }

  async function openJob(id) {
    if (state.jobAbort) state.jobAbort.abort();
    stopPlaying();
    const abort = new AbortController();
    state.jobAbort = abort;
    state.jobId = id;
    state.scene = null;
    state.loss = { records: [], live: false };
    Object.assign(exposed, { ready: false, jobId: id, boxes: 0, objects: 0, points: 0, times: 0, timeIndex: 0, lossRecords: 0, probe: null, error: null });
    for (const li of document.querySelectorAll('#jobs li')) li.classList.toggle('selected', li.dataset.jobId === id);
    if (!id) {
      showJobView(false);
      return;
    }
    showJobView(true);
    $('job-title').textContent = `Job ${id}`;
    $('job-summary').textContent = 'loading...';
    clearCanvas($('scene'));
    drawLoss();
    try {
      const job = await api(`/v1/jobs/${encodeURIComponent(id)}`, { signal: abort.signal });
      $('job-title').textContent = `Job ${short(job.id)} · ${job.method}`;
      $('job-summary').textContent = progressText(job);
      if (job.status === 'succeeded') {
        await loadScene(job, abort.signal);
        return;
      }
      if (job.status === 'failed' || job.status === 'cancelled') {
        setStatus(`The job is ${job.status}: nothing to show.`, job.status === 'failed');
        return;
      }
      // Running or queued: its loss as it goes, then the scene once it has succeeded.
      state.loss.live = true;
      let last = job;
      await follow(id, (event, update) => {
        last = update;
        $('job-summary').textContent = progressText(update);
        updateJobItem(update);
        const p = update.progress;
        const records = state.loss.records;
        if (p && p.loss && p.iteration > 0 && !(records.length && records[records.length - 1].iteration === p.iteration)) {
          records.push({ iteration: p.iteration, loss: p.loss });
          drawLoss();
        }
      }, abort.signal);
      if (state.jobAbort !== abort) return;
      if (last.status === 'succeeded') await loadScene(last, abort.signal);
      else setStatus(`The job is ${last.status}.`, last.status === 'failed');
    } catch (e) {
      report(e, `Job ${short(id)}`);
    }
  }

  async function loadScene(job, signal) {
    const id = encodeURIComponent(job.id);
    const [sequence, objects, losses] = await Promise.all([
      api(`/v1/sequences/${encodeURIComponent(job.sequence_id)}`, { signal }),
      api(`/v1/jobs/${id}/objects`, { signal }),
      api(`/v1/jobs/${id}/losses`, { signal }),
    ]);
    let poses = null;
    try {
      poses = (await api(`/v1/jobs/${id}/poses`, { signal })).poses;
    } catch (e) {
      // 409: the fit worked in each frame's sensor coordinates; so is the view then.
      if (!(e instanceof ApiError && e.status === 409)) throw e;
    }
    state.loss = { records: losses.losses, live: false, best: losses.best_iteration };
    drawLoss();
    $('loss-summary').textContent = `${losses.iterations} iterations; ${losses.losses.length} recorded`
      + (losses.best_iteration ? `; checkpoint at iteration ${losses.best_iteration} (validation ${fmt(losses.best_validation_loss, 4)})` : '');
    const unit = sequence.time_unit === 's' ? 's' : 'frame';
    state.scene = { job, sequence, objects, poses, unit, frame: null };
    $('job-summary').textContent = `${sequence.name || short(sequence.id)}: ${sequence.frames} frames, `
      + `${objects.objects.length} moving bod${objects.objects.length === 1 ? 'y' : 'ies'}`
      + (poses ? '' : ' · no poses: each time in its own sensor coordinates');
    const frameSelect = $('frame');
    frameSelect.replaceChildren(...objects.times.map((t, k) => Object.assign(document.createElement('option'), {
      value: String(k), textContent: `${k} (${sequence.time_unit === 's' ? `${t.toFixed(2)} s` : `t = ${t}`})`,
    })));
    frameSelect.value = '0';
    const slider = $('time');
    slider.max = String(objects.times.length - 1);
    slider.value = '0';
    await loadFrame(0, signal);
    state.camera = initialCamera(state.scene.frame);
    draw();
    setStatus('');
    exposed.ready = true;
  }

  // Queries the frame's points (a subsample of a large frame) at every frame time.
  async function loadFrame(k, signal) {
    const { job, sequence, objects, poses } = state.scene;
    const times = objects.times;
    const n = sequence.points_per_frame[k];
    let want = Math.min(n, MAX_POINTS, Math.max(1, Math.floor(MAX_POSITIONS / times.length)));
    let answer = null;
    let indices = null;
    // A server with smaller query limits than ours answers 422 `limit-exceeded`: ask for fewer.
    for (;;) {
      indices = want >= n ? null : Array.from({ length: want }, (_, i) => Math.floor((i * n) / want));
      const body = { frame: k, times };
      if (indices) body.indices = indices;
      try {
        answer = await api(`/v1/jobs/${encodeURIComponent(job.id)}/query`, { method: 'POST', json: body, signal });
        break;
      } catch (e) {
        if (!(e instanceof ApiError && e.problem && e.problem.limit) || want <= 1) throw e;
        want = Math.max(1, Math.floor(want / 2));
      }
    }
    const count = answer.positions.length;
    const T = times.length;
    const world = new Float32Array(count * T * 3);
    const toWorld = times.map((_, j) => (poses ? poses[j] : IDENTITY));
    for (let i = 0; i < count; i++) {
      const row = answer.positions[i];
      for (let j = 0; j < T; j++) {
        const [x, y, z] = apply(toWorld[j], row[j][0], row[j][1], row[j][2]);
        const at = (i * T + j) * 3;
        world[at] = x;
        world[at + 1] = y;
        world[at + 2] = z;
      }
    }
    // Speed at each time: towards the next frame (the last frame: from the one before).
    const speed = new Float32Array(count * T);
    const maxSpeed = new Float32Array(count);
    for (let i = 0; i < count; i++) {
      for (let j = 0; j < T; j++) {
        const a = j + 1 < T ? j : j - 1;
        const b = a + 1;
        const p = (i * T + a) * 3;
        const q = (i * T + b) * 3;
        const d = Math.hypot(world[q] - world[p], world[q + 1] - world[p + 1], world[q + 2] - world[p + 2]);
        const v = d / Math.max(1e-9, times[b] - times[a]);
        speed[i * T + j] = v;
        if (v > maxSpeed[i]) maxSpeed[i] = v;
      }
    }
    // Each point's body: the first whose box (at the point's own frame) holds it.
    const bodies = objects.objects.map((o) => ({ id: o.id, toBody: rigidInverse(o.poses_sensor[k]), min: o.extent.min_m, max: o.extent.max_m }));
    const object = new Int32Array(count).fill(-1);
    for (let i = 0; i < count; i++) {
      const p = answer.positions[i][k];
      for (const b of bodies) {
        const [x, y, z] = apply(b.toBody, p[0], p[1], p[2]);
        if (x >= b.min[0] - BOX_MARGIN_M && x <= b.max[0] + BOX_MARGIN_M && y >= b.min[1] - BOX_MARGIN_M
          && y <= b.max[1] + BOX_MARGIN_M && z >= b.min[2] - BOX_MARGIN_M && z <= b.max[2] + BOX_MARGIN_M) {
          object[i] = b.id;
          break;
        }
      }
    }
    // The fastest points carry trails; the fastest of all is the probe the test follows.
    const order = Array.from({ length: count }, (_, i) => i).sort((a, b) => maxSpeed[b] - maxSpeed[a]);
    const trails = order.filter((i) => maxSpeed[i] > STILL_SPEED).slice(0, MAX_TRAILS);
    const all = Array.from(speed);
    const speedScale = Math.max(2 * STILL_SPEED, quantile(all.filter((v) => v > STILL_SPEED), 0.95));
    state.scene.frame = { k, count, T, world, speed, object, trails, probe: order[0], speedScale };
    exposed.points = count;
    exposed.times = T;
    exposed.objects = objects.objects.length;
  }

  // --- the 3D view -----------------------------------------------------------------------

  function initialCamera(frame) {
    const { count, T, world, k } = frame;
    const xs = [];
    const ys = [];
    const zs = [];
    for (let i = 0; i < count; i++) {
      const at = (i * T + k) * 3;
      xs.push(world[at]);
      ys.push(world[at + 1]);
      zs.push(world[at + 2]);
    }
    const span = Math.max(quantile(xs, 0.95) - quantile(xs, 0.05), quantile(ys, 0.95) - quantile(ys, 0.05), 5);
    return {
      target: [quantile(xs, 0.5), quantile(ys, 0.5), quantile(zs, 0.5)],
      yaw: -Math.PI / 2, // looking along +x, the sensor's forward
      pitch: 0.85,
      distance: 0.85 * span,
    };
  }

  // World point -> canvas pixel, or null behind the eye.
  function projector(canvas, camera) {
    const { target, yaw, pitch, distance } = camera;
    const cy = Math.cos(yaw);
    const sy = Math.sin(yaw);
    const cp = Math.cos(pitch);
    const sp = Math.sin(pitch);
    const focal = 0.9 * canvas.height;
    const w2 = canvas.width / 2;
    const h2 = canvas.height / 2;
    return (x, y, z) => {
      const dx = x - target[0];
      const dy = y - target[1];
      const dz = z - target[2];
      // Into the yawed frame, whose +y is the viewing direction on the ground.
      const x1 = cy * dx + sy * dy;
      const y1 = -sy * dx + cy * dy;
      // Relative to the eye at (0, -d cos p, d sin p), looking at the target.
      const vy = y1 + distance * cp;
      const vz = dz - distance * sp;
      const depth = cp * vy - sp * vz;
      if (depth < 0.1) return null;
      const up = sp * vy + cp * vz;
      return [w2 + (focal * x1) / depth, h2 - (focal * up) / depth];
    };
  }

  function clearCanvas(canvas) {
    const ctx = canvas.getContext('2d');
    ctx.fillStyle = canvas.id === 'scene' ? BACKGROUND : '#ffffff';
    ctx.fillRect(0, 0, canvas.width, canvas.height);
  }

  function speedColour(v, scale) {
    if (v < STILL_SPEED) return '#5b6b82';
    const u = Math.min(1, v / scale);
    const bucket = Math.round(u * 12) / 12;
    return `hsl(${Math.round(200 - 200 * bucket)}, 90%, 55%)`;
  }

  function objectColour(id) {
    return id < 0 ? '#5b6b82' : `hsl(${Math.round((id * 137.508) % 360)}, 85%, 60%)`;
  }

  const BOX_EDGES = [[0, 1], [1, 3], [3, 2], [2, 0], [4, 5], [5, 7], [7, 6], [6, 4], [0, 4], [1, 5], [2, 6], [3, 7]];

  function draw() {
    const canvas = $('scene');
    clearCanvas(canvas);
    const scene = state.scene;
    if (!scene || !scene.frame || !state.camera) return;
    const ctx = canvas.getContext('2d');
    const project = projector(canvas, state.camera);
    const { count, T, world, speed, object, trails, speedScale } = scene.frame;
    const j = Number($('time').value);
    const byObject = $('colour').value === 'object';
    const colourOf = (i) => (byObject ? objectColour(object[i]) : speedColour(speed[i * T + j], speedScale));

    if ($('trails').checked) {
      ctx.lineWidth = 1;
      for (const i of trails) {
        ctx.strokeStyle = colourOf(i);
        ctx.globalAlpha = 0.45;
        ctx.beginPath();
        let drawing = false;
        for (let s = 0; s < T; s++) {
          const at = (i * T + s) * 3;
          const p = project(world[at], world[at + 1], world[at + 2]);
          if (!p) {
            drawing = false;
            continue;
          }
          if (drawing) ctx.lineTo(p[0], p[1]);
          else ctx.moveTo(p[0], p[1]);
          drawing = true;
        }
        ctx.stroke();
      }
      ctx.globalAlpha = 1;
    }

    // Points at time j, one path per colour.
    const buckets = new Map();
    let drawn = 0;
    for (let i = 0; i < count; i++) {
      const at = (i * T + j) * 3;
      const p = project(world[at], world[at + 1], world[at + 2]);
      if (!p) continue;
      const colour = colourOf(i);
      let list = buckets.get(colour);
      if (!list) buckets.set(colour, (list = []));
      list.push(p);
      drawn++;
    }
    for (const [colour, list] of buckets) {
      ctx.fillStyle = colour;
      ctx.beginPath();
      for (const p of list) ctx.rect(p[0] - 1, p[1] - 1, 2, 2);
      ctx.fill();
    }

    // The moving bodies' boxes at time j.
    let boxes = 0;
    if ($('boxes').checked) {
      const { objects, poses } = scene;
      ctx.lineWidth = 1.5;
      for (const o of objects.objects) {
        const toWorld = compose(poses ? poses[j] : IDENTITY, o.poses_sensor[j]);
        const { min_m: lo, max_m: hi } = o.extent;
        const corners = [];
        for (let c = 0; c < 8; c++) {
          const w = apply(toWorld, c & 4 ? hi[0] : lo[0], c & 2 ? hi[1] : lo[1], c & 1 ? hi[2] : lo[2]);
          corners.push(project(w[0], w[1], w[2]));
        }
        ctx.strokeStyle = objectColour(o.id);
        ctx.beginPath();
        let edges = 0;
        for (const [a, b] of BOX_EDGES) {
          if (!corners[a] || !corners[b]) continue;
          ctx.moveTo(corners[a][0], corners[a][1]);
          ctx.lineTo(corners[b][0], corners[b][1]);
          edges++;
        }
        ctx.stroke();
        if (edges) boxes++;
      }
    }

    const at = (scene.frame.probe * T + j) * 3;
    exposed.probe = scene.frame.count ? project(world[at], world[at + 1], world[at + 2]) : null;
    exposed.boxes = boxes;
    exposed.timeIndex = j;
    canvas.dataset.boxes = String(boxes);
    canvas.dataset.points = String(drawn);
    canvas.dataset.timeIndex = String(j);
    const t = scene.objects.times[j];
    $('time-label').textContent = scene.unit === 's' ? `${t.toFixed(2)} s (frame ${j})` : `frame ${j}`;
    $('legend').textContent = byObject
      ? 'Colour: the moving body whose box holds the point at its frame; grey: none.'
      : `Colour: speed, blue slow to red ${fmt(speedScale, 1)} m/${scene.unit === 's' ? 's' : 'frame'} and more; grey: still.`;
  }

  // --- the loss curve --------------------------------------------------------------------

  function drawLoss() {
    const canvas = $('loss');
    clearCanvas(canvas);
    const records = state.loss.records;
    exposed.lossRecords = records.length;
    canvas.dataset.records = String(records.length);
    const ctx = canvas.getContext('2d');
    ctx.font = '12px system-ui, sans-serif';
    ctx.fillStyle = '#667085';
    if (!records.length) {
      ctx.fillText(state.loss.live ? 'waiting for the first iteration...' : 'no loss recorded', 12, 20);
      return;
    }
    // Windows count their iterations from 1 again: their records are then placed one after another.
    const windowed = records.some((r) => r.window !== undefined);
    const xs = records.map((r, i) => (windowed ? i + 1 : r.iteration));
    const series = [records.map((r) => r.loss.total), records.map((r) => (r.validation ? r.validation.total : null))];
    const values = series.flat().filter((v) => v !== null && Number.isFinite(v));
    const log = values.every((v) => v > 0);
    const f = (v) => (log ? Math.log10(v) : v);
    let lo = Math.min(...values.map(f));
    let hi = Math.max(...values.map(f));
    if (hi - lo < 1e-12) {
      lo -= 0.5;
      hi += 0.5;
    }
    const left = 60;
    const right = canvas.width - 12;
    const top = 12;
    const bottom = canvas.height - 28;
    const x0 = Math.min(...xs);
    const x1 = Math.max(x0 + 1, Math.max(...xs));
    const px = (x) => left + ((x - x0) / (x1 - x0)) * (right - left);
    const py = (v) => bottom - ((f(v) - lo) / (hi - lo)) * (bottom - top);
    ctx.strokeStyle = '#d8dde6';
    ctx.strokeRect(left, top, right - left, bottom - top);
    ctx.fillText(fmt(log ? 10 ** hi : hi), 4, top + 10);
    ctx.fillText(fmt(log ? 10 ** lo : lo), 4, bottom);
    ctx.fillText(windowed ? `record ${x0}` : `iteration ${x0}`, left, bottom + 18);
    const end = `${x1}`;
    ctx.fillText(end, right - ctx.measureText(end).width, bottom + 18);
    ctx.strokeStyle = '#2563eb';
    ctx.lineWidth = 1.5;
    ctx.beginPath();
    records.forEach((r, i) => {
      const p = [px(xs[i]), py(r.loss.total)];
      if (i) ctx.lineTo(...p);
      else ctx.moveTo(...p);
    });
    ctx.stroke();
    ctx.fillStyle = '#f79009';
    records.forEach((r, i) => {
      if (!r.validation) return;
      ctx.beginPath();
      ctx.arc(px(xs[i]), py(r.validation.total), 3, 0, 2 * Math.PI);
      ctx.fill();
    });
    ctx.fillStyle = '#1d2330';
    const legend = `total loss (blue${log ? ', log scale' : ''}), validation (orange)`;
    ctx.fillText(legend, right - ctx.measureText(legend).width - 4, top + 14);
  }

  // --- controls --------------------------------------------------------------------------

  function wireControls() {
    $('token-form').addEventListener('submit', (event) => {
      event.preventDefault();
      state.token = $('token').value.trim();
      if (state.token) sessionStorage.setItem(TOKEN_KEY, state.token);
      else sessionStorage.removeItem(TOKEN_KEY);
      $('token').value = '';
      setStatus(state.token ? 'Token saved for this tab.' : 'Token cleared.');
      exposed.error = null;
      refreshLists();
      if (state.jobId) openJob(state.jobId);
    });
    $('time').addEventListener('input', draw);
    $('colour').addEventListener('change', draw);
    $('trails').addEventListener('change', draw);
    $('boxes').addEventListener('change', draw);
    $('frame').addEventListener('change', async () => {
      if (!state.scene) return;
      const signal = state.jobAbort && state.jobAbort.signal;
      try {
        await loadFrame(Number($('frame').value), signal);
        draw();
      } catch (e) {
        report(e, 'Loading the frame');
      }
    });
    $('play').addEventListener('click', () => {
      if (state.playTimer) {
        stopPlaying();
        return;
      }
      $('play').textContent = 'Pause';
      state.playTimer = setInterval(() => {
        const slider = $('time');
        slider.value = String((Number(slider.value) + 1) % (Number(slider.max) + 1));
        draw();
      }, 200);
    });
    $('reset-view').addEventListener('click', () => {
      if (state.scene && state.scene.frame) state.camera = initialCamera(state.scene.frame);
      draw();
    });

    const canvas = $('scene');
    let drag = null;
    canvas.addEventListener('contextmenu', (event) => event.preventDefault());
    canvas.addEventListener('pointerdown', (event) => {
      if (!state.camera) return;
      drag = { x: event.clientX, y: event.clientY, pan: event.shiftKey || event.button !== 0 };
      canvas.setPointerCapture(event.pointerId);
    });
    canvas.addEventListener('pointermove', (event) => {
      if (!drag || !state.camera) return;
      const dx = event.clientX - drag.x;
      const dy = event.clientY - drag.y;
      drag.x = event.clientX;
      drag.y = event.clientY;
      const cam = state.camera;
      if (drag.pan) {
        // Along the ground, in the view's right and forward directions.
        const s = cam.distance / canvas.clientHeight;
        const cy = Math.cos(cam.yaw);
        const sy = Math.sin(cam.yaw);
        cam.target[0] += s * (-dx * cy - dy * sy);
        cam.target[1] += s * (-dx * sy + dy * cy);
      } else {
        cam.yaw -= dx * 0.006;
        cam.pitch = Math.min(1.55, Math.max(0.05, cam.pitch + dy * 0.006));
      }
      draw();
    });
    const endDrag = () => { drag = null; };
    canvas.addEventListener('pointerup', endDrag);
    canvas.addEventListener('pointercancel', endDrag);
    canvas.addEventListener('wheel', (event) => {
      if (!state.camera) return;
      event.preventDefault();
      state.camera.distance = Math.min(1e4, Math.max(0.5, state.camera.distance * Math.exp(event.deltaY * 0.001)));
      draw();
    }, { passive: false });

    window.addEventListener('popstate', () => openJob(new URLSearchParams(location.search).get('job')));
  }

  wireControls();
  refreshLists();
  openJob(new URLSearchParams(location.search).get('job'));
})();
