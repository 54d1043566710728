// The viewer page in headless Chromium against a real `mbnt serve` (started by ./run, with a
// token): uploads the simulated sequence in $SIM_DIR, fits it, then checks what a person would
// see: the page asks for the token and then lists the sequence and the job; `/?job=ID` draws the
// points and one box per moving body; the time slider moves the points; the loss curve is drawn.
//
// Environment: MBNT_URL, MBNT_TOKEN, SIM_DIR, CHROMIUM (the browser), PLAYWRIGHT_DIR (where
// playwright-core is installed), SCREENSHOT_DIR (optional: screenshots are kept there).
'use strict';

const test = require('node:test');
const assert = require('node:assert/strict');
const fs = require('node:fs');
const path = require('node:path');

const { chromium } = require(require.resolve('playwright-core', { paths: [process.env.PLAYWRIGHT_DIR] }));

const url = process.env.MBNT_URL;
const token = process.env.MBNT_TOKEN;
const simDir = process.env.SIM_DIR;
const BACKGROUND = [0x0f, 0x14, 0x1c];

async function api(route, init = {}) {
  const response = await fetch(url + route, {
    ...init,
    headers: { Authorization: `Bearer ${token}`, ...(init.headers || {}) },
  });
  const body = await response.json();
  if (!response.ok) throw new Error(`${init.method || 'GET'} ${route}: ${response.status} ${JSON.stringify(body)}`);
  return body;
}

let browser;
let page;
let job;
let objects;
const consoleErrors = [];

test.before(async () => {
  // The simulated sequence, uploaded as `mbnt simulate` wrote it, and a short fit of it.
  const frameDir = path.join(simDir, 'frames');
  const form = new FormData();
  const lines = (name) => fs.readFileSync(path.join(simDir, name), 'utf8').trim().split('\n');
  form.append('meta', JSON.stringify({
    name: 'viewer-test',
    timestamps: lines('timestamps.txt').map(Number),
    poses: lines('poses.txt').map((l) => l.trim().split(/\s+/).map(Number)),
  }));
  for (const file of fs.readdirSync(frameDir).sort()) {
    form.append('frame', new Blob([fs.readFileSync(path.join(frameDir, file))]), file);
  }
  const sequence = await api('/v1/sequences', { method: 'POST', body: form });
  job = await api('/v1/jobs', {
    method: 'POST',
    headers: { 'Content-Type': 'application/json' },
    body: JSON.stringify({ sequence_id: sequence.id, method: 'mbnt', params: { iterations: 5 } }),
  });
  const started = Date.now();
  while (job.status !== 'succeeded') {
    assert.ok(!['failed', 'cancelled'].includes(job.status), `the fit ended ${job.status}: ${job.error}`);
    assert.ok(Date.now() - started < 120_000, 'the fit took over two minutes');
    await new Promise((resolve) => setTimeout(resolve, 250));
    job = await api(`/v1/jobs/${job.id}`);
  }
  objects = (await api(`/v1/jobs/${job.id}/objects`)).objects;
  // Boxes drawn must be compared with something: the simulated street has moving cars.
  assert.ok(objects.length > 0, 'the fit found no moving body to draw');

  browser = await chromium.launch({ executablePath: process.env.CHROMIUM, headless: true });
  page = await browser.newPage({ viewport: { width: 1300, height: 1100 } });
  page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(m.text()); });
  page.on('pageerror', (e) => consoleErrors.push(`uncaught: ${e.message}`));
});

test.after(async () => {
  if (browser) await browser.close();
});

async function screenshot(name) {
  if (process.env.SCREENSHOT_DIR) await page.screenshot({ path: path.join(process.env.SCREENSHOT_DIR, `${name}.png`) });
}

// The canvas's pixels that differ from its background, and a digest of them.
async function canvasPixels(id, background) {
  return page.evaluate(([id, bg]) => {
    const canvas = document.getElementById(id);
    const data = canvas.getContext('2d').getImageData(0, 0, canvas.width, canvas.height).data;
    let lit = 0;
    let hash = 0;
    for (let i = 0; i < data.length; i += 4) {
      if (Math.abs(data[i] - bg[0]) + Math.abs(data[i + 1] - bg[1]) + Math.abs(data[i + 2] - bg[2]) > 30) {
        lit++;
        hash = (hash * 31 + i) | 0;
      }
    }
    return { lit, hash, total: data.length / 4 };
  }, [id, background]);
}

test('the page asks for the token, then lists the sequence and the job', async () => {
  await page.goto(`${url}/`);
  await page.waitForSelector('#token-form.needed');
  assert.match(await page.textContent('#status'), /needs an API token/);
  // The only errors so far are the browser's notes of the refused calls.
  assert.ok(consoleErrors.every((e) => e.includes('401')), consoleErrors.join('\n'));
  consoleErrors.length = 0;

  await page.fill('#token', token);
  await page.click('#token-form button');
  await page.waitForSelector(`#jobs li[data-job-id="${job.id}"]`);
  assert.match(await page.textContent('#sequences'), /viewer-test/);
  assert.match(await page.textContent(`#jobs li[data-job-id="${job.id}"]`), /succeeded/);
  assert.equal(await page.evaluate(() => sessionStorage.getItem('mbnt-api-token')), token);
  assert.deepEqual(consoleErrors, []);
});

test('/?job=ID draws the points and a box for every moving body', async () => {
  // The token stays in the tab's session storage across the navigation.
  await page.goto(`${url}/?job=${job.id}`);
  await page.waitForFunction(() => window.mbntViewer.ready || window.mbntViewer.error, null, { timeout: 60_000 });
  const viewer = await page.evaluate(() => window.mbntViewer);
  assert.equal(viewer.error, null);
  assert.equal(viewer.jobId, job.id);
  assert.equal(viewer.objects, objects.length);
  assert.equal(viewer.boxes, objects.length, 'one box drawn per moving body');
  assert.equal(await page.getAttribute('#scene', 'data-boxes'), String(objects.length));
  assert.ok(viewer.points > 100, `${viewer.points} points shown`);
  const pixels = await canvasPixels('scene', BACKGROUND);
  assert.ok(pixels.lit > 500, `only ${pixels.lit} pixels drawn`);
  await screenshot('job');
  assert.deepEqual(consoleErrors, []);
});

test('moving the time slider moves the points', async () => {
  const before = await page.evaluate(() => window.mbntViewer);
  const pixelsBefore = await canvasPixels('scene', BACKGROUND);
  const last = before.times - 1;
  await page.$eval('#time', (slider, value) => {
    slider.value = String(value);
    slider.dispatchEvent(new Event('input', { bubbles: true }));
  }, last);
  const after = await page.evaluate(() => window.mbntViewer);
  assert.equal(after.timeIndex, last);
  // The fastest point, projected on the canvas, has moved (pixels).
  const moved = Math.hypot(after.probe[0] - before.probe[0], after.probe[1] - before.probe[1]);
  assert.ok(moved > 3, `the fastest point moved ${moved.toFixed(1)} px`);
  const pixelsAfter = await canvasPixels('scene', BACKGROUND);
  assert.notEqual(pixelsAfter.hash, pixelsBefore.hash, 'the canvas did not change');
  assert.equal(after.boxes, objects.length);
  await screenshot('job-last-frame');
  assert.deepEqual(consoleErrors, []);
});

test('the loss curve shows every recorded iteration', async () => {
  const losses = await api(`/v1/jobs/${job.id}/losses`);
  assert.equal(await page.evaluate(() => window.mbntViewer.lossRecords), losses.losses.length);
  assert.ok(losses.losses.length >= 5);
  const pixels = await canvasPixels('loss', [255, 255, 255]);
  assert.ok(pixels.lit > 200, `only ${pixels.lit} pixels of the loss curve drawn`);
  // Colouring by object draws the same scene in other colours, without errors.
  await page.selectOption('#colour', 'object');
  assert.equal(await page.evaluate(() => window.mbntViewer.boxes), objects.length);
  assert.deepEqual(consoleErrors, []);
});

test('a running job shows its progress and loss live, and its end', async () => {
  const sequenceId = job.sequence_id;
  const running = await api('/v1/jobs', {
    method: 'POST',
    headers: { 'Content-Type': 'application/json' },
    body: JSON.stringify({ sequence_id: sequenceId, method: 'mbnt', params: { iterations: 50 } }),
  });
  await page.goto(`${url}/?job=${running.id}`);
  // Loss records arrive through the job's event stream while it fits.
  await page.waitForFunction(() => window.mbntViewer.lossRecords >= 2, null, { timeout: 60_000 });
  const live = await api(`/v1/jobs/${running.id}`);
  assert.notEqual(live.status, 'succeeded', 'the fit ended before the page saw it run: give it more iterations');
  assert.match(await page.textContent('#job-summary'), /running · \d+\/50 it · loss/);
  await api(`/v1/jobs/${running.id}/cancel`, { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: '{}' });
  await page.waitForFunction(() => /cancelled/.test(document.getElementById('status').textContent), null, { timeout: 30_000 });
  assert.equal(await page.evaluate(() => window.mbntViewer.ready), false);
  assert.deepEqual(consoleErrors, []);
});
