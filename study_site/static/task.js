/* Click-to-find task. No build step, no dependencies.
 *
 * 1. GET the participant's remaining trials (opaque image URLs only: lossless WebP, PNG fallback).
 * 2. Preload and decode every image before the first trial, so download time never counts.
 * 3. Per trial: POST /api/start (the server starts the trial's clock the first time and answers with the
 *    time already used, so a reload continues the same deadline), show the image at a fixed share of the
 *    viewport, start the page's clock (performance.now) after it is painted, wait for one click or the
 *    remaining time, POST the answer (retried until acknowledged; kept in localStorage so a reload
 *    re-sends it) with the displayed size, viewport and device pixel ratio, then show the reveal image.
 * 4. After every trial is acknowledged, POST /api/complete and go to the completion page.
 */
(function () {
  'use strict';

  var root = document.getElementById('task');
  if (!root) return;
  var CSRF = root.dataset.csrf;
  var URLS = { state: root.dataset.state, start: root.dataset.start, trial: root.dataset.trial,
               complete: root.dataset.complete };

  function $(id) { return document.getElementById(id); }
  var stage = $('stage'), panel = $('panel'), panelText = $('panel-text'), panelButton = $('panel-button');
  var loadFill = $('load-fill'), timerBox = $('timer'), timerFill = $('timer-fill'), statusEl = $('status'), nextBtn = $('next');
  var phaseEl = $('phase'), counterEl = $('counter'), progressFill = $('progress-fill');

  function Fatal(message) { this.message = message; }
  function sleep(ms) { return new Promise(function (r) { setTimeout(r, ms); }); }
  function frame() { return new Promise(function (r) { requestAnimationFrame(function () { r(); }); }); }
  function randomId() {
    var a = new Uint8Array(16);
    crypto.getRandomValues(a);
    return Array.prototype.map.call(a, function (b) { return ('0' + b.toString(16)).slice(-2); }).join('');
  }

  function showStatus(text, kind) {
    statusEl.textContent = text || '';
    statusEl.className = 'status' + (kind ? ' ' + kind : '');
  }

  /* JSON request, retried with backoff on network errors, 408, 429 and 5xx until acknowledged. */
  async function request(url, body) {
    var delay = 300, attempt = 0;
    for (;;) {
      var res = null, data = null;
      try {
        var opts = { credentials: 'same-origin', cache: 'no-store', headers: { 'Accept': 'application/json' } };
        if (body !== undefined) {
          opts.method = 'POST';
          opts.headers['Content-Type'] = 'application/json';
          opts.headers['X-CSRF-Token'] = CSRF;
          opts.body = JSON.stringify(body);
        }
        res = await fetch(url, opts);
        data = await res.json();
      } catch (e) {
        data = null;
      }
      if (res && res.ok && data) return data;
      if (res && (res.status === 401 || res.status === 409)) {
        if (data && data.redirect) {
          window.location.href = data.redirect;
          await new Promise(function () {});
        }
        throw new Fatal((data && data.error) || 'The session is out of step.');
      }
      if (res && res.status >= 400 && res.status < 500 && res.status !== 408 && res.status !== 429) {
        throw new Fatal((data && data.error) || ('Request failed (' + res.status + ').'));
      }
      attempt += 1;
      if (attempt >= 2) showStatus('Saving\u2026 the connection is slow, retrying', 'info');
      await sleep(delay + Math.random() * delay * 0.3);
      delay = Math.min(delay * 2, 8000);
    }
  }

  var state = null;
  var images = new Map();
  function pendingKey() { return 'camo-study-pending-' + state.key; }
  function savePending(body) { try { localStorage.setItem(pendingKey(), JSON.stringify(body)); } catch (e) { /* private mode */ } }
  function loadPending() { try { return JSON.parse(localStorage.getItem(pendingKey()) || 'null'); } catch (e) { return null; } }
  function clearPending() { try { localStorage.removeItem(pendingKey()); } catch (e) { /* ignore */ } }

  function setPhase(name) { root.dataset.phase = name; }

  /* The image sits in a frame with the time bar right under it (same width). */
  var frameEl = document.createElement('div');
  frameEl.className = 'frame';
  function showImage(el) {
    timerBox.hidden = false;
    frameEl.replaceChildren(el, timerBox);
    stage.replaceChildren(frameEl);
  }

  function showPanel(text, loading) {
    setPhase(loading ? 'loading' : 'panel');
    panelText.textContent = text;
    loadFill.parentNode.hidden = !loading;
    panelButton.hidden = true;
    stage.replaceChildren(panel);
  }
  function panelWait(text, label) {
    showPanel(text, false);
    panelButton.textContent = label;
    panelButton.hidden = false;
    panelButton.focus();
    return new Promise(function (resolve) {
      panelButton.onclick = function () { panelButton.onclick = null; resolve(); };
    });
  }

  function setProgress(t) {
    var nPractice = state.practice, nFormal = state.total - state.practice;
    if (t.practice) {
      phaseEl.textContent = 'Practice';
      phaseEl.className = 'phase practice';
      counterEl.textContent = 'Practice ' + (t.index + 1) + ' of ' + nPractice;
    } else {
      phaseEl.textContent = 'Main task';
      phaseEl.className = 'phase';
      counterEl.textContent = 'Image ' + (t.index - nPractice + 1) + ' of ' + nFormal;
    }
    progressFill.style.width = (100 * t.index / state.total) + '%';
  }

  async function preload(trials) {
    var done = 0;
    showPanel('Loading images\u2026', true);
    loadFill.style.width = '0%';
    await Promise.all(trials.map(async function (t) {
      var img = new Image();
      img.alt = 'Find the hidden object and click on it';
      img.draggable = false;
      var url = t.src;  // lossless WebP; the same pixels as PNG (t.fallback) for a browser without WebP
      for (var attempt = 0; ; attempt++) {
        img.src = url;
        try { await img.decode(); break; } catch (e) {
          if (url !== t.fallback && t.fallback) { url = t.fallback; continue; }
          if (attempt >= 5) throw new Fatal('An image could not be loaded. Please check your connection and reload the page.');
          await sleep(500 * (attempt + 1));
        }
      }
      images.set(t.index, img);
      done += 1;
      loadFill.style.width = (100 * done / trials.length) + '%';
    }));
  }

  function startTimerBar(remaining, limit) {
    timerFill.style.transition = 'none';
    timerFill.style.width = (100 * remaining / limit) + '%';
    void timerFill.offsetWidth;
    timerFill.style.transition = 'width ' + remaining + 'ms linear';
    timerFill.style.width = '0%';
  }
  function stopTimerBar() {
    var w = getComputedStyle(timerFill).width;
    timerFill.style.transition = 'none';
    timerFill.style.width = w;
  }

  /* The image's size is a fixed share of the viewport: height = height_share * viewport height, unless
     that makes it wider than max_width_share * viewport width. Same share for every participant. */
  function fitImage(img) {
    var d = state.display, vw = window.innerWidth, vh = window.innerHeight;
    var aspect = img.naturalWidth / img.naturalHeight;
    var h = d.height_share * vh, w = h * aspect;
    if (w > d.max_width_share * vw) { w = d.max_width_share * vw; h = w / aspect; }
    img.style.width = Math.round(w) + 'px';
    img.style.height = Math.round(h) + 'px';
  }
  async function ensureViewport() {
    var d = state.display;
    while (window.innerWidth < d.min_viewport_w || window.innerHeight < d.min_viewport_h) {
      await panelWait('Please make this window larger (at least ' + d.min_viewport_w + ' \u00d7 ' +
        d.min_viewport_h + ' pixels; now ' + window.innerWidth + ' \u00d7 ' + window.innerHeight +
        '), e.g. by maximising it, then press Continue.', 'Continue');
    }
  }
  function sizes(img) {
    var r = img.getBoundingClientRect();
    return { display_w: r.width, display_h: r.height, viewport_w: window.innerWidth,
             viewport_h: window.innerHeight, dpr: window.devicePixelRatio || 1 };
  }

  /* Start the trial on the server, show the image, return {timed_out, x, y, rt_ms, sizes..., fx, fy}.
     rt_ms counts from the trial's first start: after a reload the time already used is included. */
  async function present(t) {
    await ensureViewport();
    var img = images.get(t.index);
    var limit = state.time_limit_ms;
    var start = await request(URLS.start, { trial_index: t.index });
    if (start.remaining_ms <= 0) {
      return Object.assign({ timed_out: true, rt_ms: limit }, sizes(img)); // a timeout's time is the limit
    }
    img.className = 'stim';
    fitImage(img);
    showImage(img);
    await frame();
    await frame(); // the image has been painted
    var base = start.elapsed_ms, remaining = start.remaining_ms;
    var t0 = performance.now();
    startTimerBar(remaining, limit);
    return new Promise(function (resolve) {
      var finished = false;
      function end(r) {
        if (finished) return;
        finished = true;
        clearTimeout(timer);
        img.removeEventListener('pointerdown', onDown);
        stopTimerBar();
        resolve(r);
      }
      function onDown(e) {
        if (e.button !== 0) return;
        var rt = base + performance.now() - t0;
        e.preventDefault();
        var r = img.getBoundingClientRect();
        var fx = (e.clientX - r.left) / r.width, fy = (e.clientY - r.top) / r.height;
        var x = Math.min(img.naturalWidth - 1, Math.max(0, Math.floor(fx * img.naturalWidth)));
        var y = Math.min(img.naturalHeight - 1, Math.max(0, Math.floor(fy * img.naturalHeight)));
        end(Object.assign({ timed_out: false, x: x, y: y, rt_ms: rt, fx: fx, fy: fy }, sizes(img)));
      }
      img.addEventListener('pointerdown', onDown);
      setPhase('trial');
      var timer = setTimeout(function () {
        // a timer that fired late (a sleeping laptop) is still a timeout; its time is capped near the limit
        var rt = Math.min(Math.max(limit, base + performance.now() - t0), limit + 60000);
        end(Object.assign({ timed_out: true, rt_ms: rt }, sizes(img)));
      }, remaining);
    });
  }

  async function showReveal(url, answer, shown) {
    var rev = new Image();
    rev.alt = 'Where the object was';
    rev.draggable = false;
    rev.src = url;
    try { await rev.decode(); } catch (e) { rev = shown; /* keep the image; the answer is saved anyway */ }
    rev.className = 'stim revealed';
    fitImage(rev);
    showImage(rev);
    if (!answer.timed_out) {
      var r = rev.getBoundingClientRect(), f = frameEl.getBoundingClientRect();
      var m = document.createElement('div');
      m.className = 'marker';
      m.style.left = (r.left - f.left + answer.fx * r.width) + 'px';
      m.style.top = (r.top - f.top + answer.fy * r.height) + 'px';
      frameEl.appendChild(m);
    }
  }

  function waitNext(label) {
    nextBtn.textContent = label;
    nextBtn.hidden = false;
    nextBtn.focus();
    return new Promise(function (resolve) {
      nextBtn.onclick = function () { nextBtn.onclick = null; nextBtn.hidden = true; resolve(); };
    });
  }

  async function runTrial(t, isLast) {
    setProgress(t);
    showStatus('Click on the hidden object', 'info');
    nextBtn.hidden = true;
    var a = await present(t);
    var body = { trial_index: t.index, client_trial_id: randomId(), timed_out: a.timed_out, rt_ms: a.rt_ms,
                 display_w: a.display_w, display_h: a.display_h, viewport_w: a.viewport_w,
                 viewport_h: a.viewport_h, dpr: a.dpr };
    if (!a.timed_out) { body.x = a.x; body.y = a.y; }
    savePending(body);
    setPhase('saving');
    showStatus('Saving\u2026', 'info');
    var resp = await request(URLS.trial, body);
    clearPending();
    progressFill.style.width = (100 * (t.index + 1) / state.total) + '%';
    await showReveal(resp.reveal, a, images.get(t.index));
    if (resp.late) showStatus('Too late: time was up before your click. Here is where the object was.', 'bad');
    else if (resp.timed_out) showStatus('Time is up. Here is where the object was.', 'bad');
    else if (resp.hit) showStatus('Found it! (' + (a.rt_ms / 1000).toFixed(1) + ' s)', 'good');
    else showStatus('Not quite. Here is where the object was.', 'bad');
    setPhase('reveal');
    await waitNext(isLast ? 'Finish' : 'Next image');
    showStatus('', '');
  }

  async function finish() {
    showStatus('', '');
    showPanel('Saving your results\u2026', false);
    var r = await request(URLS.complete, {});
    setPhase('done');
    window.location.href = r.redirect;
  }

  async function main() {
    state = await request(URLS.state);
    var pending = loadPending();
    if (pending && pending.trial_index === state.next) {
      showPanel('Saving your last answer\u2026', false);
      await request(URLS.trial, pending);
      clearPending();
      state = await request(URLS.state);
    } else if (pending) {
      clearPending();
    }
    var trials = state.trials;
    if (!trials.length) return finish();
    await preload(trials);
    for (var i = 0; i < trials.length; i++) {
      var t = trials[i], prev = i > 0 ? trials[i - 1] : null;
      if (i === 0) {
        var first = t.index === 0 && !t.started
          ? 'Practice first: find the hidden object in each image and click on it as quickly as you can.'
          : 'Welcome back. You continue with ' + (t.practice ? 'the practice.' : 'the main task.') +
            (t.started ? ' The image you were looking at continues with the time that was left.' : '');
        setProgress(t);
        await panelWait(first, t.practice ? 'Start the practice' : 'Continue');
      } else if (prev.practice && !t.practice) {
        setProgress(t);
        await panelWait('Practice complete. From now on your answers count. ' +
          'There are ' + (state.total - state.practice) + ' images.', 'Start the main task');
      }
      await runTrial(t, i === trials.length - 1);
    }
    await finish();
  }

  stage.addEventListener('contextmenu', function (e) { e.preventDefault(); });
  main().catch(function (e) {
    var msg = e instanceof Fatal ? e.message : 'Something went wrong.';
    showStatus('', '');
    showPanel(msg + ' Reloading the page continues where you stopped.', false);
    setPhase('error');
    panelButton.textContent = 'Reload';
    panelButton.hidden = false;
    panelButton.onclick = function () { window.location.reload(); };
    if (window.console) console.error(e);
  });
})();
