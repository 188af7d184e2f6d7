// The operator's screen. Plain JavaScript (no framework, nothing fetched from elsewhere): the live stream is
// server-sent events from /api/events; actions are POSTs with the session's CSRF token.
'use strict';

const $ = (id) => document.getElementById(id);
let csrf = null;
let stream = null;
const shown = [];          // newest first, at most kRows
const kRows = 30;

function fmt(v, digits) {
  return v === null || v === undefined ? '–' : Number(v).toFixed(digits);
}

function cell(row, text) {
  const td = document.createElement('td');
  td.textContent = text;
  row.appendChild(td);
}

function resultClass(r) {
  if (r.code === 'ok') return 'ok';
  if (r.code === 'unknown part' || r.code === 'ambiguous' || r.code === 'no part') return 'unknown';
  return 'fault';
}

// The picture is rendered by the server shortly after the result (a thinned copy of the scan): asked for once the
// result is shown, and again a little later if it was not ready yet.
function showPicture(acq, attempt) {
  const img = $('last-picture');
  const probe = new Image();
  probe.onload = () => { if (shown.length && shown[0].acq_id === acq) { img.src = probe.src; img.hidden = false; } };
  probe.onerror = () => { if (attempt < 5) setTimeout(() => showPicture(acq, attempt + 1), 300); };
  probe.src = '/api/live/' + acq + '.png';
}

function showLast(r) {
  if (r.code !== 'no part' && r.code !== 'bad scan') showPicture(r.acq_id, 0);
  const card = $('last');
  card.className = 'card last ' + resultClass(r);
  $('last-part').textContent = r.code === 'ok' ? r.part : r.code;
  $('last-detail').textContent =
      (r.code === 'ok' ? 'PLC id ' + r.part_id + ' · confidence ' + fmt(r.confidence, 3) + ' · ' + r.source
                       : (r.reason ? 'why: ' + r.reason : r.source)) +
      ' · cycle ' + fmt(r.cycle_ms, 1) + ' ms · acq ' + r.acq_id;
  const t = $('last-pose');
  t.textContent = '';
  const head = document.createElement('tr');
  ['', 'x mm', 'y mm', 'z mm', 'rx °', 'ry °', 'θ °'].forEach((h) => {
    const th = document.createElement('th');
    th.textContent = h;
    head.appendChild(th);
  });
  t.appendChild(head);
  const keys = ['x_mm', 'y_mm', 'z_mm', 'rx_deg', 'ry_deg', 'theta_deg'];
  const pose = document.createElement('tr');
  cell(pose, 'pose');
  keys.forEach((k, i) => cell(pose, fmt(r.pose[k], i < 3 ? 2 : 3)));
  t.appendChild(pose);
  const sigma = document.createElement('tr');
  cell(sigma, '1σ');
  keys.forEach((k, i) => cell(sigma, fmt(r.sigma[k], i < 3 ? 2 : 3)));
  t.appendChild(sigma);
}

function renderResults() {
  const body = $('results');
  body.textContent = '';
  for (const r of shown) {
    const row = document.createElement('tr');
    row.className = resultClass(r);
    row.dataset.id = r.id;
    cell(row, r.seq || '–');
    cell(row, new Date(r.time_ms).toLocaleTimeString());
    cell(row, r.code);
    cell(row, r.part || '–');
    cell(row, r.part_id || '–');
    cell(row, fmt(r.confidence, 3));
    cell(row, r.source);
    cell(row, fmt(r.pose.x_mm, 2));
    cell(row, fmt(r.pose.y_mm, 2));
    cell(row, fmt(r.pose.theta_deg, 3));
    cell(row, fmt(r.cycle_ms, 1));
    body.appendChild(row);
  }
}

function addResult(r) {
  if (shown.length && shown[0].id >= r.id) return;
  shown.unshift(r);
  if (shown.length > kRows) shown.pop();
  showLast(r);
  renderResults();
}

function table(id, rows) {
  const t = $(id);
  t.textContent = '';
  for (const [k, v] of rows) {
    const row = document.createElement('tr');
    cell(row, k);
    cell(row, v === undefined || v === null ? '–' : String(v));
    t.appendChild(row);
  }
}

function showStatus(s) {
  const state = $('state');
  state.textContent = s.state + (s.error && s.error !== 'none' ? ': ' + s.error : '');
  state.className = 'badge ' + (s.state === 'fault' ? 'bad' : s.warning && s.warning !== 'none' ? 'warn' : 'ok');
  const plc = $('plc');
  const connected = s.plc ? s.plc.clients_connected : 0;
  plc.textContent = 'PLC ' + (connected > 0 ? 'connected (' + connected + ')' : 'not connected');
  plc.className = 'badge ' + (connected > 0 ? 'ok' : 'warn');
  const c = s.counters || {};
  const codes = s.results_by_code || {};
  table('counters', [['parts', c.results], ['recognised', codes.ok], ['unknown', codes['unknown part']],
    ['ambiguous', codes.ambiguous], ['timeouts', c.timeouts], ['faults', c.faults],
    ['missed triggers', c.missed_triggers]]);
  const cy = s.cycle || {};
  table('health-loop', [['state', s.state], ['error', s.error], ['warning', s.warning],
    ['last cycle ms', fmt(cy.last_ms, 1)], ['max cycle ms', fmt(cy.max_ms, 1)], ['deadline ms', cy.deadline_ms],
    ['deadline margin ms', cy.deadline_ms !== undefined ? fmt(cy.deadline_ms - cy.max_ms, 1) : null],
    ['faults', c.faults], ['recoveries', c.recoveries], ['late decisions', c.late_decisions],
    ['real-time scheduling', s.realtime ? s.realtime.applied : null], ['models', s.models ? s.models.dir : null]]);
  const p = s.plc || {};
  table('health-plc', [['clients connected', p.clients_connected], ['results published', p.results_published],
    ['results acknowledged', p.results_acked], ['queue depth', p.queue_depth], ['PLC heartbeat losses',
      p.heartbeat_losses], ['clients evicted', p.clients_evicted], ['requests served', p.requests_served]]);
  const h = s.hmi || {};
  showHistogram(s.cycle_histogram);
  showFaults(s.fault_log);
  showInForce(s.in_force);
  table('health-hmi', [['live views', h.live_streams], ['sessions', h.sessions], ['results taken', h.results_taken],
    ['results dropped', h.results_dropped]]);
}

function showHistogram(h) {
  const box = $('health-histogram');
  box.textContent = '';
  if (!h || !h.counts) return;
  const most = Math.max(1, ...h.counts);
  h.counts.forEach((n, i) => {
    const low = i === 0 ? 0 : h.upper_ms[i - 1];
    const label = h.upper_ms[i] === null ? '> ' + low + ' ms' : low + '–' + h.upper_ms[i] + ' ms';
    const bar = cs.el('span', {class: 'bar'});
    bar.style.width = (100 * n / most) + '%';
    box.append(cs.el('div', {class: 'hist-row'}, cs.el('span', {class: 'hist-label'}, label),
        cs.el('span', {class: 'hist-bar'}, bar), cs.el('span', {class: 'hist-count'}, String(n))));
  });
}

function showFaults(list) {
  const t = $('health-faults');
  t.textContent = '';
  if (!list || !list.length) { t.append(cs.el('tr', {}, cs.el('td', {}, 'none since start'))); return; }
  t.append(cs.el('tr', {}, cs.el('th', {}, 'since'), cs.el('th', {}, 'error'), cs.el('th', {}, 'recovered after')));
  for (const f of list) {
    const after = f.until_ms === null ? 'not yet' : ((f.until_ms - f.since_ms) / 1000).toFixed(1) + ' s';
    t.append(cs.el('tr', {}, cs.el('td', {}, new Date(f.since_ms).toLocaleString()), cs.el('td', {}, f.error),
        cs.el('td', {}, after)));
  }
}

function showInForce(f) {
  if (!f) return;
  const rows = [];
  for (const [name, label] of [['calibration', 'calibration'], ['manifest', 'model database'], ['svm', 'SVM']]) {
    const x = f[name];
    if (!x) continue;
    rows.push([label, x.file]);
    rows.push(['  changed', x.modified_unix_s ? new Date(x.modified_unix_s * 1000).toLocaleString() : x.error]);
    rows.push(['  CRC-32', x.crc32]);
  }
  if (f.since_unix_s) rows.push(['in force since', new Date(f.since_unix_s * 1000).toLocaleString()]);
  table('health-inforce', rows);
}

function connect() {
  if (stream) stream.close();
  stream = new EventSource('/api/events');
  stream.addEventListener('result', (e) => addResult(JSON.parse(e.data)));
  stream.addEventListener('status', (e) => showStatus(JSON.parse(e.data)));
  stream.onerror = () => { $('state').textContent = 'reconnecting'; $('state').className = 'badge warn'; };
}

async function refreshSession() {
  const s = await (await fetch('/api/session')).json();
  csrf = s.csrf || null;
  cs.session = s;
  cs.sessionHooks.forEach((fn) => fn(s));
  $('who').textContent = s.user ? s.user + ' (' + s.role + ')' : '';
  $('login-open').hidden = !!s.user;
  $('logout').hidden = !s.user;
  $('no-view').hidden = s.may_view;
  $('live').hidden = !s.may_view || $('tab-live').className.indexOf('active') < 0;
  if (s.may_view) {
    const list = await (await fetch('/api/results')).json();
    list.results.slice(-kRows).forEach(addResult);
    connect();
  } else if (stream) {
    stream.close();
  }
  return s;
}

async function post(path, body) {
  const headers = {'Content-Type': 'application/json'};
  if (csrf) headers['X-CSRF-Token'] = csrf;
  return fetch(path, {method: 'POST', headers, body: JSON.stringify(body || {})});
}

// What the other pages' scripts (parts.js, review.js, debug.js) use: the session, JSON calls with the CSRF token,
// and a call when their tab is opened or the session changes.
const cs = {
  session: null,
  tabHooks: {},
  sessionHooks: [],
  onTab(name, fn) { this.tabHooks[name] = fn; },
  onSession(fn) { this.sessionHooks.push(fn); },
  async get(path) {
    const res = await fetch(path);
    const body = await res.json().catch(() => ({}));
    if (!res.ok) throw new Error(body.error || res.statusText);
    return body;
  },
  async post(path, body) {
    const res = await post(path, body);
    const answer = await res.json().catch(() => ({}));
    if (!res.ok) throw new Error(answer.error || res.statusText);
    return answer;
  },
  el(tag, attrs, ...children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === 'class') e.className = v; else if (k.startsWith('on')) e[k] = v; else e.setAttribute(k, v);
    }
    for (const c of children) e.append(c instanceof Node ? c : String(c));
    return e;
  },
  fmt,
};
window.cs = cs;

$('login-open').onclick = () => { $('login').hidden = false; $('login-user').focus(); };
$('login-cancel').onclick = () => { $('login').hidden = true; };
$('login-form').onsubmit = async (e) => {
  e.preventDefault();
  const res = await post('/api/login', {user: $('login-user').value, password: $('login-password').value});
  const body = await res.json();
  if (!res.ok) { $('login-error').textContent = body.error; return; }
  $('login-password').value = '';
  $('login-error').textContent = '';
  $('login').hidden = true;
  await refreshSession();
};
$('logout').onclick = async () => { await post('/api/logout'); await refreshSession(); };
document.querySelectorAll('nav .tab').forEach((b) => {
  b.onclick = () => {
    document.querySelectorAll('nav .tab').forEach((t) => t.classList.toggle('active', t === b));
    document.querySelectorAll('.page').forEach((p) => { p.hidden = p.id !== b.dataset.tab; });
    if (cs.tabHooks[b.dataset.tab]) cs.tabHooks[b.dataset.tab]();
  };
});
refreshSession();
