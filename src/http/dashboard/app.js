// mcdenoise dashboard: the queue, each job's before/after, the models and the daemon.
//
// Plain JavaScript, no dependencies. Every datum comes from the daemon's own API under
// /v1, called with the bearer token the user typed; the token lives in this tab's
// sessionStorage only. Event streams are read with fetch() and a stream reader (an
// EventSource cannot send an Authorization header, and a token never goes in a URL).
// Previews are fetched the same way and shown through blob: URLs. The DOM is built with
// createElement and text nodes only (never innerHTML), so no job field can inject markup.
'use strict';

const TOKEN_KEY = 'mcdenoise.token';
const PAGE_SIZE = 50;
const REFRESH_MS = 3000;
/** Event streams the queue view keeps open at most (browsers allow 6 HTTP/1.1 connections per origin). */
const MAX_STREAMS = 4;
const STATES = ['queued', 'running', 'succeeded', 'failed', 'cancelled'];
const PRIORITIES = ['high', 'normal', 'low'];
const STAGES = ['queue', 'decode', 'preprocess', 'inference', 'reconstruction', 'encode'];

// --- DOM helpers ---------------------------------------------------------------------

/** An element with attributes (`on*` are listeners, `class`, `for`, booleans) and children. */
function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith('on')) el.addEventListener(k.slice(2), v);
    else if (k === 'dataset') Object.assign(el.dataset, v);
    else if (v === true) el.setAttribute(k, '');
    else el.setAttribute(k, String(v));
  }
  return append(el, ...children);
}

function append(el, ...children) {
  for (const c of children.flat(Infinity)) {
    if (c === undefined || c === null || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

const $ = (sel, root = document) => root.querySelector(sel);

function fmtNum(v, digits = 0) {
  if (v === null || v === undefined || Number.isNaN(v)) return '–';
  return Number(v).toLocaleString('en-US', { maximumFractionDigits: digits, minimumFractionDigits: digits });
}

function fmtMs(ms) {
  if (ms === null || ms === undefined) return '–';
  if (ms < 1000) return `${fmtNum(ms, ms < 10 ? 1 : 0)} ms`;
  if (ms < 120000) return `${fmtNum(ms / 1000, 2)} s`;
  return `${fmtNum(ms / 60000, 1)} min`;
}

function fmtBytes(n) {
  if (n === null || n === undefined) return '–';
  const units = ['B', 'KB', 'MB', 'GB'];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) { n /= 1024; i++; }
  return `${fmtNum(n, i ? 1 : 0)} ${units[i]}`;
}

function fmtTime(iso) {
  if (!iso) return '–';
  const d = new Date(iso);
  const now = new Date();
  const sameDay = d.toDateString() === now.toDateString();
  return sameDay ? d.toLocaleTimeString() : d.toLocaleString();
}

function duration(job) {
  if (job.timings_ms) return fmtMs(job.timings_ms.total);
  if (job.started_at && job.state === 'running') return fmtMs(Date.now() - Date.parse(job.started_at));
  return '–';
}

function badge(state) { return h('span', { class: `badge ${state}` }, state); }

function progressBar(job) {
  const p = job.progress || { tiles_done: 0, tiles_total: 0 };
  const frac = job.state === 'succeeded' ? 1 : p.tiles_total ? p.tiles_done / p.tiles_total : 0;
  const bar = h('div', {
    class: `bar${job.state === 'succeeded' ? ' done' : ''}`, role: 'progressbar',
    'aria-valuemin': 0, 'aria-valuemax': 100, 'aria-valuenow': Math.round(frac * 100),
    'aria-label': `progress of job ${job.id}`,
  }, h('span'));
  bar.firstChild.style.setProperty('--p', `${(frac * 100).toFixed(1)}%`);
  return h('div', { class: 'progress' }, bar,
    h('span', { class: 't' }, p.tiles_total ? `${p.tiles_done}/${p.tiles_total}` : ''));
}

// --- The API ---------------------------------------------------------------------------

class Unauthorized extends Error {}

class ApiError extends Error {
  constructor(status, code, message) { super(message); this.status = status; this.code = code; }
}

function token() { return sessionStorage.getItem(TOKEN_KEY) || ''; }

/** fetch() on the daemon with the token; JSON errors become ApiError, 401 Unauthorized. */
async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  if (token()) headers.set('Authorization', `Bearer ${token()}`);
  const res = await fetch(path, { ...options, headers, cache: 'no-store', credentials: 'omit' });
  if (res.status === 401) throw new Unauthorized('the daemon needs a valid token');
  if (!res.ok) {
    let code = 'error';
    let message = `${res.status} ${res.statusText}`;
    try {
      const body = await res.json();
      if (body && body.error) { code = body.error.code; message = body.error.message; }
    } catch (_) { /* not JSON */ }
    throw new ApiError(res.status, code, message);
  }
  return res;
}

async function apiJson(path, options) { return (await api(path, options)).json(); }

/**
 * Reads a Server-Sent Events stream with the token: calls onEvent(name, data) per event
 * and resolves when the stream ends. Aborted through `signal`.
 */
async function readEvents(path, onEvent, signal) {
  const res = await api(path, { signal, headers: { Accept: 'text/event-stream' } });
  const reader = res.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = '';
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value.replace(/\r\n?/g, '\n');
    let end;
    while ((end = buffer.indexOf('\n\n')) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let name = 'message';
      const data = [];
      for (const line of block.split('\n')) {
        if (!line || line.startsWith(':')) continue;
        const colon = line.indexOf(':');
        const field = colon < 0 ? line : line.slice(0, colon);
        let v = colon < 0 ? '' : line.slice(colon + 1);
        if (v.startsWith(' ')) v = v.slice(1);
        if (field === 'event') name = v;
        else if (field === 'data') data.push(v);
      }
      if (data.length) onEvent(name, JSON.parse(data.join('\n')));
    }
  }
}

// --- Application state -------------------------------------------------------------------

const app = {
  /** Cleanup of the current view (timers, streams, object URLs). */
  cleanups: [],
  info: null,
  models: null,
};

function onLeave(fn) { app.cleanups.push(fn); }

function leaveView() {
  for (const fn of app.cleanups.splice(0)) {
    try { fn(); } catch (_) { /* already gone */ }
  }
}

function setConn(text, bad = false) {
  const el = $('#conn');
  el.textContent = text;
  el.classList.toggle('bad', bad);
}

function showLogin(message) {
  leaveView();
  $('#view').replaceChildren();
  $('#login').hidden = false;
  $('#signout').hidden = true;
  const err = $('#login-error');
  err.hidden = !message;
  err.textContent = message || '';
  setConn('not signed in', true);
  $('#token').focus();
}

/** Runs a view; a 401 anywhere shows the token prompt. */
async function guarded(fn) {
  try {
    await fn();
  } catch (e) {
    if (e instanceof Unauthorized) {
      const had = token();
      sessionStorage.removeItem(TOKEN_KEY);
      app.info = null;
      showLogin(had ? 'The daemon refused this token.' : '');
      return;
    }
    if (e.name === 'AbortError') return;
    $('#view').replaceChildren(h('p', { class: 'error', role: 'alert' }, `Error: ${e.message}`));
  }
}

async function signIn() {
  app.info = await apiJson('/v1/info');
  $('#login').hidden = true;
  $('#signout').hidden = !token();
  const scope = app.info.caller ? app.info.caller.scope : '';
  setConn(`${app.info.ready ? 'ready' : app.info.phase} · v${app.info.version}${scope ? ` · ${scope} token` : ''}`, !app.info.ready);
}

// --- Routing ------------------------------------------------------------------------------

function parseHash() {
  const raw = location.hash.replace(/^#/, '') || '/';
  const [path, query = ''] = raw.split('?');
  return { path, params: new URLSearchParams(query) };
}

async function route() {
  leaveView();
  const { path, params } = parseHash();
  const view = $('#view');
  view.replaceChildren();
  const name = path.startsWith('/jobs/') ? 'queue' : path === '/models' ? 'models' : path === '/daemon' ? 'daemon' : 'queue';
  for (const a of document.querySelectorAll('[data-nav]')) {
    if (a.dataset.nav === name) a.setAttribute('aria-current', 'page'); else a.removeAttribute('aria-current');
  }
  await guarded(async () => {
    if (!app.info) await signIn();
    if (path.startsWith('/jobs/')) await jobView(decodeURIComponent(path.slice(6)), view);
    else if (path === '/models') await modelsView(view);
    else if (path === '/daemon') await daemonView(view);
    else await queueView(params, view);
  });
}

// --- Queue view ---------------------------------------------------------------------------

function card(k, v, s) {
  return h('div', { class: 'card' }, h('div', { class: 'v' }, v), h('div', { class: 'k' }, k), s ? h('div', { class: 's' }, s) : null);
}

function totals(stats) {
  const b = stats.by_state;
  const q = stats.queued_by_priority;
  const hour = stats.last_hour;
  return h('div', { class: 'cards', id: 'totals' },
    card('queued', fmtNum(b.queued), `high ${q.high} · normal ${q.normal} · low ${q.low} · capacity ${stats.queue_capacity}`),
    card('running', fmtNum(b.running), `${stats.workers} worker${stats.workers === 1 ? '' : 's'}`),
    card('succeeded', fmtNum(b.succeeded), `failed ${fmtNum(b.failed)} · cancelled ${fmtNum(b.cancelled)}`),
    card('frames per hour', fmtNum(hour.frames_per_hour), `last hour · ${fmtNum(hour.megapixels, hour.megapixels < 10 ? 2 : 1)} MP`),
    card('seconds per megapixel', hour.mean_seconds_per_megapixel === null ? '–' : fmtNum(hour.mean_seconds_per_megapixel, 2), 'mean run time, last hour'),
    card('failed, last hour', fmtNum(hour.failed), `cancelled ${fmtNum(hour.cancelled)}`),
  );
}

function queueHash(params) {
  const q = new URLSearchParams();
  for (const [k, v] of params) if (v) q.set(k, v);
  const s = q.toString();
  return `#/${s ? `?${s}` : ''}`;
}

async function queueView(params, view) {
  const filters = {
    state: params.get('state') || '', priority: params.get('priority') || '',
    label: params.get('label') || '', client: params.get('client') || '',
    order: params.get('order') || 'newest',
  };
  // Page tokens of the pages before this one: "previous" pops them.
  const trail = (params.get('trail') || '').split('.').filter(Boolean);
  const pageToken = params.get('page') || '';

  const field = (label, control) => h('label', {}, label, control);
  const select = (name, values, all) => {
    const s = h('select', { name }, h('option', { value: '' }, all), values.map((v) => h('option', { value: v }, v)));
    s.value = filters[name];
    return s;
  };
  const form = h('form', { class: 'filters', role: 'search', 'aria-label': 'Filter jobs' },
    field('State', select('state', STATES, 'every state')),
    field('Priority', select('priority', PRIORITIES, 'every priority')),
    field('Label', h('input', { name: 'label', value: filters.label, placeholder: 'exact label' })),
    field('Client', h('input', { name: 'client', value: filters.client, placeholder: 'token:… or ip:…' })),
    field('Order', (() => {
      const s = h('select', { name: 'order' }, h('option', { value: 'newest' }, 'newest first'), h('option', { value: 'oldest' }, 'oldest first'));
      s.value = filters.order;
      return s;
    })()),
    h('button', { type: 'submit' }, 'Apply'),
    h('button', { type: 'button', onclick: () => { location.hash = '#/'; } }, 'Clear'));
  form.addEventListener('submit', (ev) => {
    ev.preventDefault();
    const data = new FormData(form);
    location.hash = queueHash(new URLSearchParams([...data.entries()].map(([k, v]) => [k, String(v).trim()])));
  });

  const totalsSlot = h('div');
  const tableSlot = h('div', { id: 'jobs' });
  const pager = h('div', { class: 'pager' });
  append(view, h('h1', {}, 'Queue'), totalsSlot, form, tableSlot, pager);

  const listQuery = () => {
    const q = new URLSearchParams({ limit: String(PAGE_SIZE), order: filters.order });
    for (const k of ['state', 'priority', 'label', 'client']) if (filters[k]) q.set(k, filters[k]);
    if (pageToken) q.set('page_token', pageToken);
    return q.toString();
  };

  const streams = new Map();
  onLeave(() => { for (const c of streams.values()) c.abort(); streams.clear(); });
  let rows = new Map();
  let timer = null;
  let stopped = false;
  onLeave(() => { stopped = true; clearTimeout(timer); });

  const render = (page) => {
    rows = new Map();
    if (!page.jobs.length) {
      tableSlot.replaceChildren(h('p', { class: 'muted' }, pageToken ? 'No more jobs.' : 'No jobs match.'));
    } else {
      const tbody = h('tbody', {}, page.jobs.map((job) => {
        const tr = jobRow(job);
        rows.set(job.id, tr);
        return tr;
      }));
      tableSlot.replaceChildren(h('table', {},
        h('thead', {}, h('tr', {},
          ['Job', 'State', 'Priority', 'Position', 'Label', 'Client', 'Size', 'Progress', 'Submitted', 'Run time', ''].map((t, i) =>
            h('th', { scope: 'col', class: i === 3 || i === 9 ? 'num' : null }, t)))),
        tbody));
    }
    const nextTrail = [...trail, pageToken || '0'].join('.');
    pager.replaceChildren(
      h('button', { type: 'button', disabled: !pageToken, onclick: () => { location.hash = '#/'; } }, 'First page'),
      h('button', {
        type: 'button', disabled: !pageToken, onclick: () => {
          const p = new URLSearchParams(parseHash().params);
          const prev = trail[trail.length - 1];
          p.set('trail', trail.slice(0, -1).join('.'));
          if (prev && prev !== '0') p.set('page', prev); else p.delete('page');
          location.hash = queueHash(p);
        },
      }, 'Previous'),
      h('button', {
        type: 'button', disabled: !page.next_page_token, onclick: () => {
          const p = new URLSearchParams(parseHash().params);
          p.set('page', page.next_page_token);
          p.set('trail', nextTrail);
          location.hash = queueHash(p);
        },
      }, 'Next page'),
      h('span', { class: 'muted' }, `${page.jobs.length} job${page.jobs.length === 1 ? '' : 's'} on this page, ${PAGE_SIZE} per page`));
  };

  const follow = (jobs) => {
    const running = jobs.filter((j) => j.state === 'running' || j.state === 'queued').slice(0, MAX_STREAMS);
    const wanted = new Set(running.map((j) => j.id));
    for (const [id, c] of streams) if (!wanted.has(id)) { c.abort(); streams.delete(id); }
    for (const job of running) {
      if (streams.has(job.id)) continue;
      const c = new AbortController();
      streams.set(job.id, c);
      readEvents(`/v1/jobs/${encodeURIComponent(job.id)}/events`, (name, data) => {
        const tr = rows.get(job.id);
        if (!tr) return;
        const cur = tr.job;
        let next = null;
        if (name === 'progress') next = { ...cur, state: 'running', progress: { tiles_done: data.tiles_done, tiles_total: data.tiles_total } };
        else if (name === 'started') next = { ...cur, state: 'running', queue_position: null };
        else if (data && data.state) next = data;
        if (next) {
          const fresh = jobRow(next);
          tr.replaceWith(fresh);
          rows.set(job.id, fresh);
        }
      }, c.signal).catch(() => {}).finally(() => { streams.delete(job.id); });
    }
  };

  const refresh = async () => {
    const [stats, page] = await Promise.all([apiJson('/v1/stats'), apiJson(`/v1/jobs?${listQuery()}`)]);
    if (stopped) return;
    totalsSlot.replaceChildren(totals(stats));
    render(page);
    follow(page.jobs);
  };
  const loop = async () => {
    if (stopped) return;
    if (!document.hidden) await guarded(refresh);
    if (!stopped) timer = setTimeout(loop, REFRESH_MS);
  };
  await refresh();
  timer = setTimeout(loop, REFRESH_MS);
}

function jobRow(job) {
  // Ids are UUIDv7: the first digits are the submission time, shared by a burst of jobs;
  // the last ones tell them apart.
  const short = job.id.slice(-8);
  const tr = h('tr', { dataset: { id: job.id, state: job.state } },
    h('td', { class: 'id' }, h('a', { href: `#/jobs/${encodeURIComponent(job.id)}`, title: job.id, 'aria-label': `job ${job.id}` }, short)),
    h('td', {}, badge(job.state)),
    h('td', { class: job.priority === 'high' ? 'prio-high' : null }, job.priority),
    h('td', { class: 'num' }, job.queue_position ?? ''),
    h('td', {}, job.label ?? ''),
    h('td', { class: 'mono' }, job.client ?? ''),
    h('td', {}, `${job.width}×${job.height}`),
    h('td', {}, progressBar(job)),
    h('td', {}, fmtTime(job.created_at)),
    h('td', { class: 'num' }, duration(job)),
    h('td', { class: 'actions' }, jobActions(job, () => route())));
  tr.job = job;
  return tr;
}

/** Cancel and delete buttons; `after` runs once the daemon has answered. */
function jobActions(job, after) {
  const finished = ['succeeded', 'failed', 'cancelled'].includes(job.state);
  const act = (label, run, cls) => h('button', {
    type: 'button', class: cls, 'aria-label': `${label} job ${job.id}`,
    disabled: label === 'Cancel' && (finished || job.cancel_requested),
    onclick: async (ev) => {
      ev.currentTarget.disabled = true;
      await guarded(async () => { await run(); await after(); });
    },
  }, label);
  return [
    act('Cancel', () => api(`/v1/jobs/${encodeURIComponent(job.id)}/cancel`, { method: 'POST' })),
    ' ',
    act('Delete', async () => {
      if (!window.confirm(`Delete job ${job.id} and its files?`)) return;
      await api(`/v1/jobs/${encodeURIComponent(job.id)}`, { method: 'DELETE' });
    }, 'danger'),
  ];
}

// --- Job view -----------------------------------------------------------------------------

async function loadModels() {
  if (!app.models) app.models = await apiJson('/v1/models');
  return app.models;
}

async function jobView(id, view) {
  let job = await apiJson(`/v1/jobs/${encodeURIComponent(id)}`);
  const head = h('div');
  const body = h('div');
  append(view, head, body);
  const controller = new AbortController();
  onLeave(() => controller.abort());
  let viewer = null;

  const draw = () => {
    head.replaceChildren(h('div', { class: 'jobhead' },
      h('h1', {}, 'Job ', h('span', { class: 'mono' }, job.id)), badge(job.state),
      h('div', { class: 'actions' },
        job.state === 'succeeded' ? h('button', { type: 'button', onclick: () => guarded(() => download(job)) }, 'Download EXR') : null,
        jobActions(job, async () => {
          try { job = await apiJson(`/v1/jobs/${encodeURIComponent(job.id)}`); draw(); } catch (e) {
            if (e instanceof ApiError && e.status === 404) { location.hash = '#/'; return; }
            throw e;
          }
        }))));
    const side = h('div', {}, summaryPanel(job), timingsPanel(job), metricsPanel(job), modelPanel(job));
    if (!viewer) viewer = new Viewer(job);
    else viewer.update(job);
    body.replaceChildren();
    append(body,
      job.error ? h('div', { class: 'panel', id: 'job-error' }, h('h2', {}, `Error: ${job.error.code}`), h('pre', { class: 'error' }, job.error.message)) : null,
      h('div', { class: 'grid2' }, h('div', {}, viewer.el), side));
  };
  draw();
  onLeave(() => viewer && viewer.dispose());
  // Loads the model list for the model panel without holding the first paint.
  loadModels().then(draw).catch(() => {});

  if (!['succeeded', 'failed', 'cancelled'].includes(job.state)) {
    readEvents(`/v1/jobs/${encodeURIComponent(id)}/events`, (name, data) => {
      if (name === 'progress') job = { ...job, state: 'running', progress: { tiles_done: data.tiles_done, tiles_total: data.tiles_total } };
      else if (name === 'started') job = { ...job, state: 'running', queue_position: null };
      else if (name === 'deleted') { location.hash = '#/'; return; }
      else if (data && data.state) job = data;
      draw();
    }, controller.signal).catch(() => {});
  }
}

async function download(job) {
  const blob = await (await api(`/v1/jobs/${encodeURIComponent(job.id)}/result`)).blob();
  const url = URL.createObjectURL(blob);
  const a = h('a', { href: url, download: `${job.label || job.id}.exr` });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

function kvTable(rows) {
  return h('table', { class: 'kv' }, h('tbody', {}, rows.filter(Boolean).map(([k, v]) => h('tr', {}, h('th', { scope: 'row' }, k), h('td', {}, v)))));
}

function summaryPanel(job) {
  return h('div', { class: 'panel' }, h('h2', {}, 'Job'),
    kvTable([
      ['state', [badge(job.state), job.cancel_requested && job.state === 'running' ? ' cancel requested' : '']],
      ['progress', progressBar(job)],
      job.queue_position ? ['queue position', job.queue_position] : null,
      ['priority', job.priority],
      ['label', job.label ?? '–'],
      ['client', h('span', { class: 'mono' }, job.client ?? '–')],
      ['frame', `${job.width}×${job.height} · ${fmtBytes(job.input_bytes)}${job.has_reference ? ' · with reference' : ''}`],
      ['variant', job.variant ?? (job.requested_variant ? `${job.requested_variant} (requested)` : 'auto')],
      ['layers', job.layers.length ? job.layers.join(', ') : 'R,G,B'],
      ['attempts', job.attempts],
      ['submitted', fmtTime(job.created_at)],
      job.started_at ? ['started', fmtTime(job.started_at)] : null,
      job.finished_at ? ['finished', fmtTime(job.finished_at)] : null,
      job.expires_at ? ['expires', fmtTime(job.expires_at)] : null,
      job.result_bytes ? ['result', fmtBytes(job.result_bytes)] : null,
      job.fireflies ? ['fireflies', `${job.fireflies.mode}, strength ${job.fireflies.strength}: ${fmtNum(job.fireflies.handled)} clamped`] : null,
      job.sanitized && job.sanitized.total ? ['non-finite samples', fmtNum(job.sanitized.total)] : null,
      job.missing_variances && job.missing_variances.length ? ['missing variances', job.missing_variances.join(', ')] : null,
      job.warnings && job.warnings.length ? ['warnings', job.warnings.join('; ')] : null,
    ]));
}

function timingsPanel(job) {
  const t = job.timings_ms;
  if (!t) return null;
  const max = Math.max(...STAGES.map((s) => t[s] || 0), 1);
  return h('div', { class: 'panel timings', id: 'timings' }, h('h2', {}, 'Timings'),
    STAGES.map((s) => {
      const b = h('div', { class: 'b' }, h('span'));
      b.firstChild.style.setProperty('--p', `${((t[s] || 0) / max * 100).toFixed(1)}%`);
      return h('div', { class: 'row' }, h('span', {}, s), b, h('span', { class: 'ms' }, fmtMs(t[s])));
    }),
    h('div', { class: 'row' }, h('strong', {}, 'total'), h('span'), h('strong', { class: 'ms' }, fmtMs(t.total))),
    h('div', { class: 'hint' }, `total is the run time, decode to result on disk; ${fmtNum(t.total / 1000 / (job.width * job.height / 1e6), 2)} s per megapixel`));
}

function metricsPanel(job) {
  if (!job.has_reference) return null;
  const m = job.metrics;
  const rows = [['relmse', 'RelMSE', false], ['dssim', 'DSSIM', false], ['psnr', 'PSNR (dB)', true], ['smape', 'SMAPE', false]];
  const content = m ? h('table', { id: 'metrics-table' },
    h('thead', {}, h('tr', {}, h('th', {}, 'metric'), h('th', { class: 'num' }, 'input'), h('th', { class: 'num' }, 'output'))),
    h('tbody', {}, rows.map(([k, name, higher]) => {
      const a = m.input[k];
      const b = m.output[k];
      const better = higher ? b > a : b < a;
      return h('tr', {}, h('th', { scope: 'row' }, name), h('td', { class: 'num' }, fmtNum(a, 4)), h('td', { class: `num${better ? ' better' : ''}` }, fmtNum(b, 4)));
    }))) : h('p', { class: 'muted' }, 'Computed against the reference once the job has succeeded.');
  const details = h('details', { class: 'panel', id: 'metrics' }, h('summary', {}, 'Quality against the reference'), content);
  if (metricsPanel.open) details.open = true;
  details.addEventListener('toggle', () => { metricsPanel.open = details.open; });
  return details;
}

function modelPanel(job) {
  if (!job.variant || !app.models) return null;
  const models = app.models.models.filter((m) => m.variant === job.variant);
  return h('div', { class: 'panel' }, h('h2', {}, `Model: ${job.variant}`),
    models.map((m) => [kvTable([
      ['component', m.component], ['contract', m.contract],
      ['FLOPs per pixel', fmtNum(m.flops_per_pixel)], ['sha256', h('span', { class: 'hash' }, m.sha256)],
    ]), h('p', { class: 'hint' }, m.architecture)]));
}

/**
 * The before/after viewer: two previews stacked, the top one clipped at the slider. Fit
 * mode shows the whole frame (at most 1600 px); a click zooms to 1:1 on the region around
 * the point, a click while zoomed moves the region, Escape or "z" goes back.
 */
class Viewer {
  constructor(job) {
    this.job = job;
    this.urls = [];
    this.exposure = 0;
    this.view = 'standard';
    this.zoom = null;
    this.seq = 0;
    const images = ['input', 'result'].concat(job.has_reference ? ['reference'] : []);
    this.left = 'input';
    this.right = 'result';
    const pick = (name, value) => {
      const s = h('select', { name, 'aria-label': name === 'left' ? 'image left of the slider' : 'image right of the slider' },
        images.map((i) => h('option', { value: i }, i)));
      s.value = value;
      s.addEventListener('change', () => { this[name] = s.value; this.load(); });
      return s;
    };
    this.exposureInput = h('input', { type: 'range', min: -8, max: 8, step: 0.5, value: 0, id: 'exposure', 'aria-label': 'exposure in stops' });
    this.exposureOut = h('output', { for: 'exposure' }, '0 EV');
    this.exposureInput.addEventListener('change', () => { this.exposure = Number(this.exposureInput.value); this.load(); });
    this.exposureInput.addEventListener('input', () => { this.exposureOut.textContent = `${this.exposureInput.value} EV`; });
    const viewSelect = h('select', { 'aria-label': 'view transform', id: 'view-transform' }, h('option', { value: 'standard' }, 'standard (sRGB)'), h('option', { value: 'filmic' }, 'filmic (ACES fit)'));
    viewSelect.addEventListener('change', () => { this.view = viewSelect.value; this.load(); });
    this.zoomButton = h('button', { type: 'button', id: 'zoom', onclick: () => (this.zoom ? this.unzoom() : this.zoomAt(0.5, 0.5)) }, 'Zoom 1:1');
    this.scale = 1;
    const scaleSelect = h('select', { 'aria-label': 'magnification when zoomed', id: 'zoom-scale' },
      [1, 2, 4, 8].map((n) => h('option', { value: n }, `${n}:1`)));
    scaleSelect.addEventListener('change', () => {
      this.scale = Number(scaleSelect.value);
      if (this.zoom) { const z = this.zoom; this.zoomAt((z.x + z.w / 2) / this.job.width, (z.y + z.h / 2) / this.job.height); }
    });

    this.before = h('img', { class: 'before', alt: '' });
    this.after = h('img', { class: 'after', alt: '' });
    this.tagL = h('span', { class: 'tag l' });
    this.tagR = h('span', { class: 'tag r' });
    this.stage = h('div', { class: 'stage' }, this.after, this.before, h('div', { class: 'divider' }), this.tagL, this.tagR);
    this.stage.addEventListener('click', (ev) => {
      const r = this.after.getBoundingClientRect();
      const fx = (ev.clientX - r.left) / r.width;
      const fy = (ev.clientY - r.top) / r.height;
      if (this.zoom) this.pan(fx, fy); else this.zoomAt(fx, fy);
    });
    this.slider = h('input', { type: 'range', min: 0, max: 100, step: 1, value: 50, id: 'slider', 'aria-label': 'before/after split, percent shown of the left image' });
    this.slider.addEventListener('input', () => this.stage.style.setProperty('--pos', `${this.slider.value}%`));
    this.box = h('div', { class: 'compare', id: 'compare' }, this.stage);
    this.placeholder = h('div', { class: 'placeholder' });
    this.onKey = (ev) => {
      if (ev.target && ['INPUT', 'SELECT', 'TEXTAREA'].includes(ev.target.tagName) && ev.target !== this.slider) return;
      if (ev.key === 'Escape' && this.zoom) this.unzoom();
      else if (ev.key === 'z' && this.ready()) { if (this.zoom) this.unzoom(); else this.zoomAt(0.5, 0.5); }
    };
    document.addEventListener('keydown', this.onKey);
    this.el = h('div', { class: 'panel', id: 'viewer' },
      h('div', { class: 'viewer-controls' },
        h('label', {}, 'left', pick('left', this.left)), h('label', {}, 'right', pick('right', this.right)),
        h('label', {}, 'exposure', this.exposureInput, this.exposureOut),
        h('label', {}, 'view', viewSelect), this.zoomButton, h('label', {}, 'zoom', scaleSelect)),
      this.box, this.placeholder,
      h('div', { class: 'slider' }, h('span', { class: 'muted' }, 'left'), this.slider, h('span', { class: 'muted' }, 'right')),
      h('div', { class: 'hint' }, 'Click the image (or press z) to zoom to 1:1 there; click again to move, Escape to fit. Previews are tone mapped by the daemon.'));
    this.load();
  }

  ready() { return this.job.state === 'succeeded'; }

  update(job) {
    const was = this.job.state;
    this.job = job;
    if (was !== job.state) this.load();
  }

  async fetchPreview(image, extra) {
    const q = new URLSearchParams({ image, exposure: String(this.exposure), view: this.view, ...extra });
    const blob = await (await api(`/v1/jobs/${encodeURIComponent(this.job.id)}/preview?${q}`)).blob();
    const url = URL.createObjectURL(blob);
    this.urls.push(url);
    return url;
  }

  region() {
    if (!this.zoom) return {};
    const z = this.zoom;
    return { region: `${z.x},${z.y},${z.w},${z.h}`, max_size: String(Math.max(z.w, z.h, 16)) };
  }

  async load() {
    const job = this.job;
    const seq = ++this.seq;
    this.tagL.textContent = this.left;
    this.tagR.textContent = this.right;
    if (!this.ready()) {
      this.box.hidden = true;
      this.placeholder.hidden = false;
      this.placeholder.textContent = job.state === 'failed' || job.state === 'cancelled'
        ? `This job ${job.state}: there is no result, and its upload was removed when it ended.`
        : 'The before/after comparison appears when the job has succeeded.';
      this.zoomButton.disabled = true;
      return;
    }
    this.box.hidden = false;
    this.placeholder.hidden = true;
    this.zoomButton.disabled = false;
    const extra = this.zoom ? this.region() : { max_size: '1600' };
    try {
      const [l, r] = await Promise.all([this.fetchPreview(this.left, extra), this.fetchPreview(this.right, extra)]);
      if (seq !== this.seq) return;
      await Promise.all([setSrc(this.before, l), setSrc(this.after, r)]);
      this.fit();
      this.stage.classList.toggle('zoomed', Boolean(this.zoom));
      this.zoomButton.textContent = this.zoom ? 'Fit' : 'Zoom 1:1';
      this.stage.dataset.loaded = `${this.left}:${this.right}:${this.zoom ? 'zoom' : 'fit'}`;
      this.revokeOld([l, r]);
    } catch (e) {
      if (e instanceof Unauthorized) throw e;
      this.placeholder.hidden = false;
      this.placeholder.textContent = `No preview: ${e.message}`;
    }
  }

  /** The stage's size: the whole frame within the panel when fitted, the region times the magnification when zoomed. */
  fit() {
    let width;
    if (this.zoom) {
      width = this.zoom.w * this.scale;
    } else {
      const maxW = Math.max(64, this.box.clientWidth - 2);
      const maxH = Math.max(64, window.innerHeight - 340);
      width = Math.floor(Math.min(maxW, maxH * this.job.width / this.job.height));
    }
    this.stage.style.width = `${width}px`;
    // Magnified pixels stay square; shrunk previews are filtered.
    this.stage.classList.toggle('magnified', width > this.after.naturalWidth);
  }

  zoomAt(fx, fy) {
    const maxW = Math.max(64, this.box.clientWidth - 4);
    const maxH = Math.max(64, window.innerHeight - 340);
    const w = Math.min(this.job.width, Math.max(16, Math.floor(maxW / this.scale)));
    const h = Math.min(this.job.height, Math.max(16, Math.floor(maxH / this.scale)));
    this.zoom = { w, h, x: 0, y: 0 };
    this.center(fx * this.job.width, fy * this.job.height);
    this.load();
  }

  pan(fx, fy) {
    const z = this.zoom;
    this.center(z.x + fx * z.w, z.y + fy * z.h);
    this.load();
  }

  center(cx, cy) {
    const z = this.zoom;
    z.x = Math.round(Math.min(Math.max(cx - z.w / 2, 0), this.job.width - z.w));
    z.y = Math.round(Math.min(Math.max(cy - z.h / 2, 0), this.job.height - z.h));
  }

  unzoom() { this.zoom = null; this.load(); }

  revokeOld(keep) {
    const old = this.urls.filter((u) => !keep.includes(u));
    this.urls = this.urls.filter((u) => keep.includes(u));
    for (const u of old) URL.revokeObjectURL(u);
  }

  dispose() {
    document.removeEventListener('keydown', this.onKey);
    for (const u of this.urls) URL.revokeObjectURL(u);
    this.urls = [];
  }
}

function setSrc(img, url) {
  return new Promise((resolve) => {
    img.onload = () => resolve();
    img.onerror = () => resolve();
    img.src = url;
  });
}

// --- Models and daemon views --------------------------------------------------------------

async function modelsView(view) {
  const [models, info] = await Promise.all([apiJson('/v1/models'), apiJson('/v1/info')]);
  app.models = models;
  const d = info.device;
  append(view, h('h1', {}, 'Models'),
    h('div', { class: 'cards' },
      card('variants', new Set(models.models.map((m) => m.variant)).size, `${models.models.length} networks`), card('tile', `${models.tile} px`),
      card('workers', models.workers, `${models.threads_per_worker} thread${models.threads_per_worker === 1 ? '' : 's'} each`),
      card('device', d.kind.toUpperCase(), `${d.cores} cores`), card('ONNX Runtime', info.onnxruntime)),
    h('table', { id: 'models' },
      h('thead', {}, h('tr', {}, ['Variant', 'Component', 'Contract', 'Architecture', 'Features', 'FLOPs / pixel', 'Radius', 'Kernel', 'Levels', 'SHA-256'].map((t, i) =>
        h('th', { scope: 'col', class: i === 5 || i === 6 ? 'num' : null }, t)))),
      h('tbody', {}, models.models.map((m) => h('tr', {},
        h('td', {}, h('strong', {}, m.variant)), h('td', {}, m.component), h('td', {}, m.contract),
        h('td', {}, m.architecture), h('td', {}, typeof m.features === 'string' ? m.features : JSON.stringify(m.features)),
        h('td', { class: 'num' }, fmtNum(m.flops_per_pixel)), h('td', { class: 'num' }, m.receptive_radius),
        h('td', {}, `${m.kernel_size}×${m.kernel_size}`), h('td', {}, m.levels),
        h('td', { class: 'hash', title: m.file }, m.sha256.slice(0, 16) + '…'))))));
}

function settingsRows(obj, prefix = '') {
  return Object.entries(obj).flatMap(([k, v]) => (v && typeof v === 'object' && !Array.isArray(v)
    ? settingsRows(v, `${prefix}${k}.`)
    : [[`${prefix}${k}`, h('span', { class: 'mono' }, v === null ? '–' : Array.isArray(v) ? v.join(', ') : String(v))]]));
}

async function daemonView(view) {
  const info = await apiJson('/v1/info');
  app.info = info;
  let ready = null;
  try {
    const res = await fetch('/readyz', { cache: 'no-store', credentials: 'omit' });
    ready = await res.json();
  } catch (_) { /* shown as unknown */ }
  const storage = ready && ready.storage;
  append(view, h('h1', {}, 'Daemon'),
    h('div', { class: 'cards' },
      card('phase', info.phase, info.ready ? 'ready' : 'not ready'),
      card('storage', storage ? (storage.ok ? 'ok' : storage.kind) : '–', storage && !storage.ok ? storage.reason : ''),
      card('uptime', fmtMs(info.uptime_seconds * 1000), `since ${fmtTime(info.started_at)}`),
      card('version', info.version, `ONNX Runtime ${info.onnxruntime}`),
      card('device', info.device.kind.toUpperCase(), `${info.device.cores} cores · ${info.device.workers} × ${info.device.threads_per_worker} threads`),
      card('your token', info.caller.scope)),
    h('h2', {}, 'Configuration'),
    info.settings
      ? h('div', { class: 'panel', id: 'settings' }, kvTable(settingsRows(info.settings)),
        h('p', { class: 'hint' }, 'As logged at start. Tokens are counted, never shown.'))
      : h('p', { class: 'muted', id: 'settings' }, 'The configuration is shown to operator tokens only.'));
}

// --- Start --------------------------------------------------------------------------------

document.addEventListener('DOMContentLoaded', () => {
  $('#login-form').addEventListener('submit', async (ev) => {
    ev.preventDefault();
    const input = $('#token');
    sessionStorage.setItem(TOKEN_KEY, input.value.trim());
    input.value = '';
    app.info = null;
    await route();
  });
  $('#signout').addEventListener('click', () => {
    sessionStorage.removeItem(TOKEN_KEY);
    app.info = null;
    app.models = null;
    showLogin('');
  });
  window.addEventListener('hashchange', route);
  route();
});
