// The parts page: the taught parts with their templates (depth picture, 3D points), delete and retrain for
// maintenance with the job's progress, and the last training's report. API: hmi/parts_api.hpp.
'use strict';
(() => {
  const el = cs.el;
  const $ = (id) => document.getElementById(id);
  const maintenance = () => !!cs.session && cs.session.role === 'maintenance';
  let poll = null;

  const head = el('tr', {}, ...['part', 'id', 'scans', 'template', 'thresholds', 'depth', ''].map((h) => el('th', {}, h)));
  $('parts').append(
      el('div', {class: 'card'}, el('div', {class: 'label'}, 'Taught parts'), el('div', {id: 'parts-summary'}),
          el('table', {id: 'parts-table', class: 'parts'}, el('thead', {}, head), el('tbody'))),
      el('div', {class: 'card job'}, el('div', {class: 'label'}, 'Job'),
          el('button', {id: 'retrain', class: 'maint'}, 'Retrain'), ' ',
          el('progress', {id: 'job-progress', max: '1'}), ' ', el('span', {id: 'job-state'}, 'no job'), ' ',
          el('button', {id: 'job-cancel', class: 'maint'}, 'Cancel'), el('pre', {id: 'job-log'})),
      el('div', {class: 'card', id: 'train-report'}, el('div', {class: 'label'}, 'Training report'),
          el('div', {id: 'train-accuracy', class: 'big'}), el('table', {id: 'train-confusion', class: 'confusion'}),
          el('pre', {id: 'train-summary'})),
      el('div', {class: 'card', id: 'part-view'}, el('div', {class: 'label', id: 'part-view-title'}),
          el('img', {id: 'part-depth', alt: 'depth image of the template'}),
          el('canvas', {id: 'part-points', width: '420', height: '420', title: 'drag to turn'})));
  $('train-report').hidden = true;
  $('part-view').hidden = true;

  const mb = (bytes) => bytes === null || bytes === undefined ? '–' : (bytes / 1e6).toFixed(1) + ' MB';

  function thresholdsText(t) {
    if (!t || !t.learnt) return 'not learnt (retrain)';
    return 'PM error ≤ ' + cs.fmt(t.max_error, 3) + ', missing ≤ ' + cs.fmt(t.max_missing_mm2, 0) +
        ' mm², extra ≤ ' + cs.fmt(t.max_extra_mm2, 0) + ' mm², size ± ' + cs.fmt(t.max_size_dev_mm, 1) + ' mm';
  }

  async function removePart(name) {
    if (!window.confirm('Delete part ' + name + ' and its scans? The SVM must be trained again afterwards.')) return;
    try {
      await cs.post('/api/parts/delete', {name});
      startPolling();
    } catch (e) { $('job-state').textContent = e.message; }
  }

  async function loadParts() {
    const list = await cs.get('/api/parts');
    const body = $('parts-table').tBodies[0];
    body.textContent = '';
    for (const p of list.parts) {
      const img = el('img', {class: 'thumb', src: '/api/parts/' + encodeURIComponent(p.name) + '/template.png',
        alt: p.name, loading: 'lazy'});
      const row = el('tr', {'data-part': p.name}, el('td', {}, p.name), el('td', {}, p.id), el('td', {}, p.scans),
          el('td', {}, mb(p.template_bytes)), el('td', {class: 'thr'}, thresholdsText(p.thresholds)), el('td', {}, img));
      const del = el('button', {class: 'delete maint', onclick: (e) => { e.stopPropagation(); removePart(p.name); }},
          'Delete');
      row.append(maintenance() ? el('td', {}, del) : el('td'));  // the operator gets no delete button at all
      row.onclick = () => showPart(p.name);
      body.append(row);
    }
    $('parts-summary').textContent = list.error ? list.error :
        list.parts.length + ' parts, ' + mb(list.total_bytes) + ' of models, SVM ' +
        (list.trained ? 'trained ' + list.svm.trained_at + ' (' + cs.fmt(100 * list.svm.test_accuracy, 1) + ' %)'
                      : 'not trained' + (list.stale_reason ? ': ' + list.stale_reason : ''));
  }

  // A simple point view: orthographic, turned by dragging, coloured by depth.
  const view = {points: [], yaw: 0, pitch: 0};
  function drawPoints() {
    const c = $('part-points');
    const g = c.getContext('2d');
    g.fillStyle = '#111';
    g.fillRect(0, 0, c.width, c.height);
    if (!view.points.length) return;
    const [cy, sy, cp, sp] = [Math.cos(view.yaw), Math.sin(view.yaw), Math.cos(view.pitch), Math.sin(view.pitch)];
    const turned = view.points.map(([x, y, z]) => {
      const x1 = cy * x + sy * z;
      const z1 = -sy * x + cy * z;
      return [x1, cp * y - sp * z1, sp * y + cp * z1];
    });
    const r = Math.max(...view.points.map(([x, y, z]) => Math.hypot(x, y, z))) || 1;
    const s = (c.width / 2 - 10) / r;
    turned.sort((a, b) => a[2] - b[2]);
    for (const [x, y, z] of turned) {
      g.fillStyle = 'hsl(' + Math.round(240 - 240 * (z / r + 1) / 2) + ',90%,55%)';
      g.fillRect(c.width / 2 + x * s, c.height / 2 - y * s, 2, 2);
    }
  }
  const canvas = $('part-points');
  canvas.onpointerdown = (e) => {
    const start = {x: e.clientX, y: e.clientY, yaw: view.yaw, pitch: view.pitch};
    canvas.onpointermove = (m) => {
      view.yaw = start.yaw + (m.clientX - start.x) / 100;
      view.pitch = start.pitch + (m.clientY - start.y) / 100;
      drawPoints();
    };
  };
  window.addEventListener('pointerup', () => { canvas.onpointermove = null; });

  async function showPart(name) {
    $('part-view').hidden = false;
    $('part-view-title').textContent = 'Template of ' + name;
    $('part-depth').src = '/api/parts/' + encodeURIComponent(name) + '/template.png';
    try {
      view.points = (await cs.get('/api/parts/' + encodeURIComponent(name) + '/points.json')).points;
    } catch (e) { view.points = []; }
    drawPoints();
  }

  function showReport(r) {
    $('train-report').hidden = false;
    $('train-accuracy').textContent = r.error ? r.error : 'SVM test accuracy ' +
        (r.accuracy === null ? 'n/a (no test scans)' : cs.fmt(100 * r.accuracy, 1) + ' %') +
        ' · CV ' + cs.fmt(100 * r.cv_accuracy, 1) + ' % · ' + r.active_features + ' features';
    const t = $('train-confusion');
    t.textContent = '';
    const names = r.classes || [];
    t.append(el('tr', {}, el('th', {}, 'true \\ recognised'), ...names.map((n) => el('th', {}, n))));
    (r.confusion || []).forEach((row, i) => {
      const total = row.reduce((a, b) => a + b, 0) || 1;
      const tr = el('tr', {}, el('th', {}, names[i] || i));
      row.forEach((n, j) => {
        const share = n / total;
        const td = el('td', {}, n);
        if (n > 0) td.style.background = i === j ? 'hsla(130,60%,45%,' + share + ')' : 'hsla(0,80%,50%,' + share + ')';
        tr.append(td);
      });
      t.append(tr);
    });
    $('train-summary').textContent = r.summary || '';
  }

  let shownJob = 0;
  async function refreshJob() {
    const j = await cs.get('/api/job');
    const running = j.state === 'running';
    $('job-progress').hidden = j.id === 0;
    if (j.progress === null) $('job-progress').removeAttribute('value'); else $('job-progress').value = j.progress;
    $('job-state').textContent = j.id === 0 ? 'no job' : j.title + ': ' + j.state +
        (j.progress_text ? ' · ' + j.progress_text : '') + (running ? '' : ' (exit code ' + j.exit_code + ')');
    $('job-log').textContent = (j.log_tail || []).slice(-12).join('\n');
    $('job-cancel').hidden = !running || !maintenance();
    $('retrain').disabled = running;
    if (!running && j.id !== shownJob) {
      shownJob = j.id;
      if (j.kind === 'train' && j.result) showReport(j.result);
      if (j.kind === 'train' || j.kind === 'delete') loadParts().catch(() => {});
    }
    if (!running && poll) { clearInterval(poll); poll = null; }
    return j;
  }
  function startPolling() {
    if (!poll) poll = setInterval(() => refreshJob().catch(() => {}), 500);
    refreshJob().catch(() => {});
  }

  $('retrain').onclick = async () => {
    if (!window.confirm('Train the SVM and the thresholds again? This takes a while; the cell keeps running.')) return;
    $('job-progress').value = 0;  // the bar is the new job's from now on, not the last one's
    try {
      await cs.post('/api/retrain', {});
      startPolling();
    } catch (e) { $('job-state').textContent = e.message; }
  };
  $('job-cancel').onclick = () => cs.post('/api/job/cancel', {}).catch((e) => { $('job-state').textContent = e.message; });

  function applyRole() {
    document.querySelectorAll('#parts .maint').forEach((b) => { b.hidden = !maintenance(); });
  }
  cs.onSession(() => {
    applyRole();
    if (!$('parts').hidden) loadParts().catch(() => {});  // the rows' buttons follow the role
  });
  cs.onTab('parts', async () => {
    applyRole();
    try {
      await loadParts();
      const j = await refreshJob();
      if (j.state === 'running') startPolling();
    } catch (e) { $('parts-summary').textContent = e.message; }
  });
})();
