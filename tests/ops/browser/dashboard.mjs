// The dashboard in headless Chromium, driven by playwright-core; run by
// tests/ops/test_dashboard.py against a real daemon. Exits 0 when every check passes and
// prints one JSON line of findings last; any failed check throws (exit 1, with the reason).
//
// Environment: DAEMON_URL, TOKEN (an operator token), FRAMES (tests/fixtures/frames),
// OUT (screenshots go there), CHROMIUM (the browser binary), PLAYWRIGHT (playwright-core's
// directory).
import { readFile } from 'node:fs/promises';
import { mkdtempSync } from 'node:fs';
import { tmpdir } from 'node:os';
import path from 'node:path';
import { createRequire } from 'node:module';

const require = createRequire(import.meta.url);
const { chromium } = require(process.env.PLAYWRIGHT);

const base = process.env.DAEMON_URL;
const origin = new URL(base).origin;
const token = process.env.TOKEN;
const frames = process.env.FRAMES;
const out = process.env.OUT;
const findings = {};

function check(cond, message) {
  if (!cond) throw new Error(`check failed: ${message}`);
}

async function submit(frame, reference, options, bytes) {
  const form = new FormData();
  form.append('options', new Blob([JSON.stringify(options)], { type: 'application/json' }));
  form.append('frame', new Blob([bytes ?? await readFile(path.join(frames, frame))]), frame);
  if (reference) form.append('reference', new Blob([await readFile(path.join(frames, reference))]), reference);
  const res = await fetch(`${base}/v1/jobs`, { method: 'POST', body: form, headers: { Authorization: `Bearer ${token}` } });
  if (res.status !== 202) throw new Error(`submission of ${frame} answered ${res.status}: ${await res.text()}`);
  return (await res.json()).id;
}

async function apiStatus(p) {
  return (await fetch(`${base}${p}`, { headers: { Authorization: `Bearer ${token}` } })).status;
}

// A fresh profile directory (playwright passes it as --user-data-dir).
const context = await chromium.launchPersistentContext(mkdtempSync(path.join(tmpdir(), 'mcdenoise-chromium-')), {
  executablePath: process.env.CHROMIUM,
  headless: true,
  args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
    '--disable-background-networking', '--disable-component-update', '--disable-sync'],
  viewport: { width: 1366, height: 800 },
  deviceScaleFactor: 1,
});
let page = null;
try {
  // Every request the page makes: those for another origin are refused and reported.
  const requests = [];
  const outside = [];
  await context.route('**/*', (route) => {
    const url = route.request().url();
    requests.push(url);
    if (new URL(url).origin !== origin) {
      outside.push(url);
      return route.abort();
    }
    return route.continue();
  });
  page = await context.newPage();
  const seen = [];
  page.on('request', (r) => seen.push(r.url()));
  const problems = [];
  process.on('exit', (code) => {
    if (code !== 0) console.error(`page errors: ${problems.join(' | ')}`);
  });
  page.on('pageerror', (e) => problems.push(`page error: ${e.message}`));
  page.on('console', (m) => {
    // A refused fetch (401 before the token) is logged as a failed resource: expected.
    if (m.type() === 'error' && !/Failed to load resource/.test(m.text())) problems.push(`console: ${m.text()}`);
  });
  page.on('dialog', (d) => d.accept());

  // Without a token: the prompt, no data, and the API refuses the page's calls.
  await page.goto(`${base}/`);
  await page.locator('#login').waitFor({ state: 'visible' });
  check(await page.locator('#view').evaluate((v) => v.childElementCount) === 0, 'no view is drawn without a token');
  findings.unauthenticated_status = await page.evaluate(() => fetch('/v1/jobs').then((r) => r.status));
  check(findings.unauthenticated_status === 401, `the API answered ${findings.unauthenticated_status} without a token`);
  // A wrong token is refused and the prompt says so.
  await page.fill('#token', 'not-the-token');
  await page.press('#token', 'Enter');
  await page.locator('#login-error').filter({ hasText: 'refused' }).waitFor();
  await page.screenshot({ path: path.join(out, 'dashboard-login.png') });

  // With the token (typed, then Enter: the keyboard path).
  await page.fill('#token', token);
  await page.press('#token', 'Enter');
  await page.locator('#totals').waitFor();
  check(!page.url().includes(token), 'the token is not in the URL');
  check(await page.evaluate(() => sessionStorage.getItem('mcdenoise.token')) !== null, 'the token is kept in session storage');

  // Jobs through the API: one with a reference (followed below), a few more for the
  // queue, one whose pixel data is cut off (it fails in the worker).
  const id = await submit('cornell-spp8.exr', 'cornell-ref.exr', { label: 'sh010', priority: 'high' });
  const cornell = await readFile(path.join(frames, 'cornell-spp8.exr'));
  const broken = await submit('cornell-spp8.exr', null, { label: 'sh030' }, cornell.subarray(0, Math.floor(cornell.length * 0.6)));
  const others = [];
  for (const [frame, ref, label, priority] of [
    ['caustic-spp8.exr', 'caustic-ref.exr', 'sh020', 'normal'], ['shadow-spp8.exr', 'shadow-ref.exr', 'sh020', 'low'],
    ['cornell-nocov-spp8.exr', null, 'sh040', 'normal'], ['caustic-spp8.exr', null, 'sh020', 'low'],
    ['shadow-spp8.exr', null, 'sh050', 'high'], ['cornell-spp8.exr', null, 'sh050', 'normal']]) {
    others.push(await submit(frame, ref, { label, priority }));
  }

  // The page follows the job to the end: its row turns succeeded with a full bar.
  const row = page.locator(`tr[data-id="${id}"]`);
  await page.locator(`tr[data-id="${id}"][data-state="succeeded"]`).waitFor({ timeout: 60000 });
  findings.progress_done = await row.locator('[role=progressbar]').getAttribute('aria-valuenow');
  check(findings.progress_done === '100', `the finished job's bar shows ${findings.progress_done}`);
  await page.locator(`tr[data-id="${broken}"][data-state="failed"]`).waitFor({ timeout: 60000 });
  for (const o of others) await page.locator(`tr[data-id="${o}"]:is([data-state="succeeded"],[data-state="failed"])`).waitFor({ timeout: 60000 });
  findings.frames_per_hour = await page.locator('#totals .card').nth(3).locator('.v').textContent();
  check(Number(findings.frames_per_hour) >= 7, `frames per hour shows ${findings.frames_per_hour}`);

  // Filters: the label filter leaves that shot's jobs.
  await page.fill('input[name=label]', 'sh020');
  await page.press('input[name=label]', 'Enter');
  await page.waitForFunction(() => {
    const rows = [...document.querySelectorAll('#jobs tbody tr')];
    return rows.length === 3 && rows.every((r) => r.children[4].textContent === 'sh020');
  });
  findings.label_filter_rows = 3;
  await page.click('text=Clear');
  await page.locator(`tr[data-id="${id}"]`).waitFor();
  await page.screenshot({ path: path.join(out, 'dashboard-queue.png') });

  // Delete from the queue view (the confirmation is accepted).
  const doomed = others[others.length - 1];
  await page.click(`tr[data-id="${doomed}"] button:has-text("Delete")`);
  await page.locator(`tr[data-id="${doomed}"]`).waitFor({ state: 'detached' });
  findings.deleted_status = await apiStatus(`/v1/jobs/${doomed}`);
  check(findings.deleted_status === 404, `the deleted job answers ${findings.deleted_status}`);

  // The job view: the before/after slider over the daemon's previews.
  await row.locator('a').click();
  await page.locator('.stage[data-loaded="input:result:fit"]').waitFor();
  const sizes = await page.$$eval('.stage img', (imgs) => imgs.map((i) => [i.naturalWidth, i.naturalHeight]));
  check(sizes.every(([w, hh]) => w === 64 && hh === 64), `previews are the frame's size: ${JSON.stringify(sizes)}`);
  await page.focus('#slider');
  for (let i = 0; i < 20; i++) await page.keyboard.press('ArrowLeft');
  findings.slider = await page.$eval('.stage', (s) => s.style.getPropertyValue('--pos'));
  check(findings.slider === '30%', `the slider moved the split to ${findings.slider}`);
  findings.clip = await page.$eval('.stage img.before', (i) => getComputedStyle(i).clipPath);
  check(findings.clip === 'inset(0px 70% 0px 0px)', `the left image shows its left 30 %: ${findings.clip}`);

  // The reference on the right, two stops brighter through the filmic view.
  await page.selectOption('select[name=right]', 'reference');
  await page.locator('.stage[data-loaded="input:reference:fit"]').waitFor();
  await page.selectOption('#view-transform', 'filmic');
  await page.$eval('#exposure', (e) => { e.value = '2'; e.dispatchEvent(new Event('input')); e.dispatchEvent(new Event('change')); });
  await page.waitForFunction(() => performance.getEntriesByType('resource').some((r) => r.name.includes('exposure=2') && r.name.includes('view=filmic')));

  // Zoom to 1:1 on a region (the keyboard's z), then back with Escape.
  await page.selectOption('select[name=right]', 'result');
  await page.locator('.stage[data-loaded="input:result:fit"]').waitFor();
  await page.locator('#exposure').blur();
  await page.focus('#slider');
  await page.keyboard.press('z');
  await page.locator('.stage[data-loaded="input:result:zoom"]').waitFor();
  check(seen.some((u) => u.includes('/preview?') && u.includes('region=')), 'the zoom asks the daemon for a region');
  await page.keyboard.press('Escape');
  await page.locator('.stage[data-loaded="input:result:fit"]').waitFor();

  // The metrics against the reference, opened.
  await page.click('#metrics summary');
  await page.locator('#metrics-table').waitFor({ state: 'visible' });
  findings.metrics = await page.$$eval('#metrics-table tbody tr', (rows) => rows.map((r) => [...r.children].map((c) => c.textContent)));
  check(findings.metrics.length === 4 && findings.metrics.every((r) => r.slice(1).every((v) => /^[0-9.,]+$/.test(v))), `metrics: ${JSON.stringify(findings.metrics)}`);
  check(await page.locator('#timings').isVisible(), 'the stage timings are shown');
  await page.$eval('#exposure', (e) => { e.value = '0'; e.dispatchEvent(new Event('input')); e.dispatchEvent(new Event('change')); });
  await page.selectOption('#view-transform', 'standard');
  await page.focus('#slider');
  for (let i = 0; i < 20; i++) await page.keyboard.press('ArrowRight');
  await page.evaluate(() => window.scrollTo(0, 0));
  await page.waitForTimeout(300);
  await page.screenshot({ path: path.join(out, 'dashboard-job.png') });

  // A failed job shows its error in full.
  await page.goto(`${base}/#/jobs/${broken}`);
  await page.locator('#job-error pre').waitFor();
  findings.error_text = await page.locator('#job-error pre').textContent();
  const job = await (await fetch(`${base}/v1/jobs/${broken}`, { headers: { Authorization: `Bearer ${token}` } })).json();
  check(findings.error_text === job.error.message, 'the error message is shown in full');

  // Models and the daemon's health and configuration.
  await page.click('nav >> text=Models');
  await page.locator('#models tbody tr').first().waitFor();
  findings.models = await page.locator('#models tbody tr').count();
  await page.screenshot({ path: path.join(out, 'dashboard-models.png') });
  await page.click('nav >> text=Daemon');
  await page.locator('#settings').waitFor();
  const text = await page.locator('body').innerText();
  check(text.includes('queue_capacity'), 'the configuration is shown to an operator');
  check(!text.includes(token), 'the token is not shown');
  await page.screenshot({ path: path.join(out, 'dashboard-daemon.png') });

  check(problems.length === 0, `errors in the page: ${problems.join(' | ')}`);
  findings.requests = requests.length;
  findings.outside = outside;
  check(outside.length === 0, `requests outside the daemon: ${outside.join(', ')}`);
  const foreign = seen.filter((u) => !u.startsWith(`${origin}/`) && !u.startsWith(`blob:${origin}/`));
  check(foreign.length === 0, `requests to other origins: ${foreign.join(', ')}`);
  check(!seen.some((u) => u.includes(token)), 'no URL carries the token');
  // The queue view reads one page at a time, whatever the store holds.
  // (Less the bare /v1/jobs this script fetched itself without a token.)
  const lists = seen.filter((u) => !u.startsWith('blob:') && new URL(u).pathname === '/v1/jobs' && new URL(u).search);
  findings.list_calls = lists.length;
  check(lists.length > 0 && lists.every((u) => new URL(u).searchParams.get('limit') === '50'), `list calls: ${lists.slice(0, 3).join(', ')}`);
  findings.ok = true;
} catch (e) {
  const view = page ? await page.locator('body').innerText().catch((err) => `(unreadable: ${err.message})`) : '';
  console.error(`the page showed: ${view}`);
  throw e;
} finally {
  await context.close();
}
console.log(JSON.stringify(findings));
