// The Review page: the scans the cell kept (unknown passes, and the passes of a part being taught), each with its
// depth image, the candidates tried and why each was refused; pick some and teach them as a part, or discard them.
// Teaching live: "Collect passes" puts the loop in teach mode (the PLC sees TEACH_MODE) and teaches the next N passes.
'use strict';

(() => {
  const page = document.getElementById('review');
  const el = cs.el;
  const fmt = cs.fmt;
  let timer = null;

  const nameInput = el('input', {id: 'teach-name', placeholder: 'part name', maxlength: '64'});
  const idInput = el('input', {id: 'teach-id', type: 'number', min: '1', max: '65535', placeholder: 'PLC id'});
  const passesInput = el('input', {id: 'teach-passes', type: 'number', min: '1', max: '50', value: '5'});
  const pickedButton = el('button', {id: 'teach-picked'}, 'Teach picked scans');
  const startButton = el('button', {id: 'teach-start'}, 'Collect passes');
  const stopButton = el('button', {id: 'teach-stop', hidden: ''}, 'Stop and teach');
  const discardButton = el('button', {id: 'discard-picked'}, 'Discard picked');
  const state = el('div', {id: 'review-job', class: 'detail'});
  const error = el('div', {id: 'review-error', class: 'error'});
  const list = el('div', {id: 'review-list'});
  const summary = el('div', {class: 'detail', id: 'review-summary'});

  page.append(
      el('div', {class: 'card'}, el('div', {class: 'label'}, 'Teach a part'),
          el('div', {class: 'row'}, el('label', {}, 'Name ', nameInput), el('label', {}, 'PLC id ', idInput),
              el('label', {}, 'Passes ', passesInput)),
          el('div', {class: 'row'}, pickedButton, startButton, stopButton, discardButton), state, error),
      el('div', {class: 'card'}, el('div', {class: 'label'}, 'Kept scans (newest first)'), summary, list));

  function picked() {
    return [...list.querySelectorAll('.pick:checked')].map((c) => Number(c.closest('.review-item').dataset.id));
  }

  function part() {
    return {name: nameInput.value.trim(), part_id: Number(idInput.value)};
  }

  async function act(fn) {
    error.textContent = '';
    try {
      await fn();
    } catch (e) {
      error.textContent = e.message;
    }
    await refresh();
  }

  pickedButton.onclick = () => act(async () => {
    const ids = picked();
    if (!ids.length) throw new Error('pick the scans of one part first');
    await cs.post('/api/review/teach', {...part(), ids});
  });
  startButton.onclick = () => act(async () => {
    await cs.post('/api/teach/start', {...part(), passes: Number(passesInput.value)});
  });
  stopButton.onclick = () => act(async () => { await cs.post('/api/teach/stop', {teach_now: true}); });
  discardButton.onclick = () => act(async () => {
    const ids = picked();
    if (!ids.length) throw new Error('pick scans first');
    await cs.post('/api/review/discard', {ids});
  });

  function candidateTable(candidates) {
    const t = el('table', {class: 'candidates'},
        el('tr', {}, ...['candidate', 'p', 'checked', 'refused by', 'value', 'limit'].map((h) => el('th', {}, h))));
    for (const c of candidates) {
      t.append(el('tr', {class: c.passed ? 'ok' : ''}, el('td', {}, c.name || '?'), el('td', {}, fmt(c.probability, 3)),
          el('td', {}, c.verified ? 'yes' : 'no'), el('td', {}, c.passed ? 'passed' : c.rejected_by),
          el('td', {}, fmt(c.value, 4)), el('td', {}, fmt(c.limit, 4))));
    }
    return t;
  }

  function item(e) {
    const when = new Date(e.time_ms).toLocaleString();
    const what = e.kind === 'teach' ? 'teach pass for PLC id ' + e.teach_part_id
                                    : (e.source === 'timeout' ? 'timeout' : 'unknown' + (e.reason ? ': ' + e.reason : ''));
    return el('div', {class: 'review-item', 'data-id': String(e.id)},
        el('label', {class: 'pick-label'}, el('input', {type: 'checkbox', class: 'pick'}), ' #' + e.id),
        el('img', {src: e.image, alt: 'depth image of scan ' + e.id, class: 'depth'}),
        el('div', {}, el('div', {}, when + ' · acq ' + e.acq_id + ' · ' + e.points + ' points'),
            el('div', {class: 'big-detail'}, what), candidateTable(e.candidates || [])));
  }

  function showSession(teach, job) {
    const collecting = teach.state === 'collecting';
    startButton.hidden = collecting;
    stopButton.hidden = !collecting;
    let text = '';
    if (collecting) text = 'teach mode: ' + teach.passes_kept + ' of ' + teach.passes_wanted + ' passes of ' + teach.name;
    else if (teach.state !== 'idle') text = 'teach ' + teach.name + ': ' + teach.state + (teach.message ? ' — ' + teach.message : '');
    if (job && job.id && (job.kind === 'teach' || job.state === 'running')) {
      text += (text ? ' · ' : '') + 'job: ' + job.title + ' ' + job.state +
          (job.progress >= 0 ? ' ' + Math.round(job.progress * 100) + ' %' : '');
    }
    state.textContent = text;
  }

  async function refresh() {
    try {
      const [review, teach, job] = await Promise.all([cs.get('/api/review'), cs.get('/api/teach'),
        cs.get('/api/job').catch(() => null)]);
      // Kept entries keep their element (and the operator's ticks): only new ones are added, gone ones removed,
      // so a click never lands on an element that a refresh replaced.
      const existing = new Map([...list.children].map((n) => [n.dataset.id, n]));
      const wanted = new Set(review.entries.map((e) => String(e.id)));
      for (const [id, node] of existing) if (!wanted.has(id)) node.remove();
      let before = list.firstChild;
      for (const e of review.entries) {
        const node = existing.get(String(e.id)) || item(e);
        if (node !== before) list.insertBefore(node, before);
        before = node.nextSibling;
      }
      summary.textContent = review.entries.length + ' kept · ' + review.stored + ' stored since start' +
          (review.failed ? ' · ' + review.failed + ' could not be stored' : '');
      showSession(teach, job);
    } catch (e) {
      error.textContent = e.message;
    }
  }

  cs.onTab('review', () => {
    refresh();
    if (!timer) timer = setInterval(() => { if (!page.hidden) refresh(); }, 3000);
  });
  cs.onSession((s) => {
    const mayAct = !!s.user;
    for (const b of [pickedButton, startButton, stopButton, discardButton]) b.disabled = !mayAct;
  });
})();
