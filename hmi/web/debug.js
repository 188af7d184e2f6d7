// The debug page (maintenance): stored scans (the review ring's, the parts' taught ones) classified again by the
// SVM alone, Perfect Match alone or the whole cascade, as a job (`classify --json`); one row per scan.
// API: hmi/parts_api.hpp.
'use strict';
(() => {
  const el = cs.el;
  const $ = (id) => document.getElementById(id);
  let waitingFor = 0;
  let poll = null;

  const mode = el('select', {id: 'debug-mode'}, el('option', {value: 'cascade'}, 'cascade (SVM + Perfect Match)'),
      el('option', {value: 'svm'}, 'SVM only'), el('option', {value: 'pm'}, 'Perfect Match only'));
  $('debug').append(
      el('div', {class: 'card'}, el('div', {class: 'label'}, 'Classify stored scans again'),
          el('label', {}, 'Mode ', mode), ' ', el('button', {id: 'debug-run'}, 'Run'), ' ',
          el('span', {id: 'debug-state'}), el('div', {id: 'debug-picker', class: 'picker'})),
      el('div', {class: 'card'}, el('div', {class: 'label'}, 'Results'),
          el('table', {id: 'debug-results', class: 'results'})));

  function check(ref, label) {
    return el('label', {class: 'scan'}, el('input', {type: 'checkbox', value: ref}), ' ' + label);
  }

  async function loadScans() {
    const s = await cs.get('/api/debug/scans');
    const picker = $('debug-picker');
    picker.textContent = '';
    const review = el('details', {open: ''}, el('summary', {}, 'Review scans (' + s.review.length + ')'));
    s.review.forEach((id) => review.append(check(id, '#' + id)));
    picker.append(review);
    for (const p of s.parts) {
      const d = el('details', {}, el('summary', {}, p.name + ' (' + p.scans.length + ' taught scans)'));
      p.scans.forEach((sc) => d.append(check(sc.ref, sc.file)));
      picker.append(d);
    }
  }

  function showResults(list) {
    const t = $('debug-results');
    t.textContent = '';
    t.append(el('tr', {}, ...['scan', 'class', 'status', 'p', 'PM error', 'x mm', 'y mm', 'θ °', 'ms', 'why']
        .map((h) => el('th', {}, h))));
    for (const d of list || []) {
      const pose = d.pose || {};
      const row = el('tr', {'data-ref': d.ref || ''}, el('td', {}, d.ref || d.scan), el('td', {}, d.class || '–'),
          el('td', {}, d.status), el('td', {}, cs.fmt(d.probability, 3)), el('td', {}, cs.fmt(d.pm_error, 3)),
          el('td', {}, cs.fmt(pose.x == null ? null : pose.x * 1e3, 2)),
          el('td', {}, cs.fmt(pose.y == null ? null : pose.y * 1e3, 2)), el('td', {}, cs.fmt(pose.theta_deg, 3)),
          el('td', {}, cs.fmt(d.ms, 1)), el('td', {}, d.class ? '' : d.reason || ''));
      row.className = d.class ? 'ok' : 'unknown';
      t.append(row);
    }
  }

  async function follow() {
    const j = await cs.get('/api/job');
    if (j.id !== waitingFor) return;
    $('debug-state').textContent = j.title + ': ' + j.state;
    if (j.state === 'running') return;
    clearInterval(poll);
    poll = null;
    showResults(j.result);
    if (j.state !== 'done') $('debug-state').textContent += ' · ' + (j.log_tail || []).slice(-3).join(' · ');
  }

  $('debug-run').onclick = async () => {
    const files = [...document.querySelectorAll('#debug-picker input:checked')].map((c) => c.value);
    if (!files.length) { $('debug-state').textContent = 'pick at least one scan'; return; }
    try {
      waitingFor = (await cs.post('/api/debug', {mode: mode.value, files})).job;
      $('debug-state').textContent = 'started';
      if (!poll) poll = setInterval(() => follow().catch(() => {}), 500);
    } catch (e) { $('debug-state').textContent = e.message; }
  };

  cs.onSession(() => { $('debug-run').disabled = !cs.session || cs.session.role !== 'maintenance'; });
  cs.onTab('debug', () => loadScans().catch((e) => { $('debug-state').textContent = e.message; }));
})();
