/* robid report: draws every [data-figure] element from the document embedded in the page
   (script#robid-data). Arrays come byte-shuffled and deflated (report/pack.py); time plots are
   decimated per view to the min and max of each pixel column from the full-rate samples, and
   their zoom is shared by every joint. */
(function () {
  "use strict";
  const t0 = performance.now();
  const doc = JSON.parse(document.getElementById("robid-data").textContent);
  const C = {meas: "#a0a0a0", model: "#1f77b4", cad: "#e07b00", resid: "#c0392b",
             raw: "rgba(120,120,120,0.55)", band: "rgba(255,170,0,0.13)", grid: "#e6e9ef",
             joints: ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2",
                      "#17becf", "#7f7f7f", "#bcbd22", "#ff7f0e"]};
  const AXIS = {stroke: "#39414f", grid: {stroke: C.grid, width: 1}, ticks: {stroke: C.grid}};
  const plots = [];       // every uPlot instance, for resizing
  const timePlots = [];   // the ones whose x (time) zoom is shared

  // ------------------------------------------------------------------ data
  function b64bytes(text) {
    const bin = atob(text);
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  // f8: float64, byte-shuffled; q: int32 steps of `step` above `lo` as first differences,
  // byte-shuffled, NaN rows as [start, stop) ranges (report/pack.py)
  async function unpack(p) {
    const size = p.dtype === "f8" ? 8 : 4;
    const stream = new Blob([b64bytes(p.z)]).stream().pipeThrough(new DecompressionStream("deflate"));
    const planes = new Uint8Array(await new Response(stream).arrayBuffer());
    if (planes.length !== size * p.n) throw new Error("packed array: " + planes.length + " bytes, expected " + size * p.n);
    const bytes = new Uint8Array(size * p.n);
    for (let b = 0; b < size; b++) {
      const off = b * p.n;
      for (let i = 0; i < p.n; i++) bytes[i * size + b] = planes[off + i];
    }
    if (p.dtype === "f8") return new Float64Array(bytes.buffer);
    const d = new Int32Array(bytes.buffer), out = new Float64Array(p.n);
    let acc = 0;
    for (let i = 0; i < p.n; i++) { acc += d[i]; out[i] = p.lo + p.step * acc; }
    for (const r of p.nan) out.fill(NaN, r[0], r[1]);
    return out;
  }

  async function unpackAll(obj) {  // every packed array in obj (recursively), in place
    const jobs = [];
    (function walk(o) {
      if (!o || typeof o !== "object") return;
      for (const k of Object.keys(o)) {
        const v = o[k];
        if (v && typeof v === "object" && typeof v.z === "string" && v.dtype) {
          jobs.push(unpack(v).then(a => { o[k] = a; }));
        } else walk(v);
      }
    })(obj);
    await Promise.all(jobs);
  }

  // ------------------------------------------------------------------ helpers
  const fmt = (v, d) => v == null || !isFinite(v) ? "—" : (+v).toPrecision(d || 4).replace(/\.?0+(e|$)/, "$1");
  const units = j => (doc.robot.joints[j - 1] || {units: {q: "rad", qd: "rad/s", qdd: "rad/s²", tau: "N·m"}}).units;
  const figs = (name, root) => Array.from((root || document).querySelectorAll('[data-figure="' + name + '"]'));
  const width = el => Math.max(200, Math.floor(el.getBoundingClientRect().width || el.parentElement.clientWidth || 400));

  function fail(el, err) {
    console.error("robid report: " + (el.dataset.figure || "figure") + ": " + err);
    el.innerHTML = '<div class="err">this figure could not be drawn: ' + String(err).replace(/</g, "&lt;") + "</div>";
  }

  function make(el, opts, data) {
    const u = new uPlot(Object.assign({width: width(el), legend: {show: true}}, opts), data, el);
    u.root.dataset.drawn = "1";
    plots.push({u: u, el: el, h: opts.height});
    return u;
  }

  function lower(a, x) {  // first index with a[i] >= x
    let lo = 0, hi = a.length;
    while (lo < hi) { const m = (lo + hi) >> 1; if (a[m] < x) lo = m + 1; else hi = m; }
    return lo;
  }

  // ------------------------------------------------------------------ decimation
  // The samples of [x0, x1]: all of them when they fit, else per pixel column the indices of
  // each series' min and max (their order kept), so every extreme is drawn at its own time.
  function decimate(t, ys, x0, x1, px) {
    const i0 = Math.max(0, lower(t, x0) - 1), i1 = Math.min(t.length, lower(t, x1) + 1);
    const n = i1 - i0;
    let idx;
    if (n <= 3 * px) {
      idx = new Array(n);
      for (let i = 0; i < n; i++) idx[i] = i0 + i;
    } else {
      idx = [];
      const per = n / px;
      for (let b = 0; b < px; b++) {
        const a = i0 + Math.floor(b * per), e = Math.min(i1, i0 + Math.floor((b + 1) * per));
        const pick = [];
        let any = false;
        for (const y of ys) {
          let lo = -1, hi = -1;
          for (let i = a; i < e; i++) {
            const v = y[i];
            if (v !== v) continue;  // NaN: a gap
            if (lo < 0 || v < y[lo]) lo = i;
            if (hi < 0 || v > y[hi]) hi = i;
          }
          if (lo >= 0) { pick.push(lo, hi); any = true; }
        }
        if (!any) { idx.push(a); continue; }  // all NaN: keep one row, it breaks the line
        pick.sort((p, q) => p - q);
        for (let k = 0; k < pick.length; k++) if (k === 0 || pick[k] !== pick[k - 1]) idx.push(pick[k]);
      }
    }
    const out = [idx.map(i => t[i])];
    for (const y of ys) out.push(idx.map(i => { const v = y[i]; return v === v ? v : null; }));
    return out;
  }

  // ------------------------------------------------------------------ time plots, linked zoom
  let syncing = false;
  function shareZoom(src) {
    if (syncing) return;
    syncing = true;
    const x = src.scales.x;
    for (const p of timePlots) if (p.u !== src) p.u.setScale("x", {min: x.min, max: x.max});
    syncing = false;
  }

  function shadeHeldOut(file) {
    return u => {
      const ctx = u.ctx, top = u.bbox.top, h = u.bbox.height;
      ctx.save();
      ctx.fillStyle = C.band;
      for (const r of file.valid || []) {
        const a = u.valToPos(r[0], "x", true), b = u.valToPos(r[1], "x", true);
        const l = Math.max(a, u.bbox.left), rr = Math.min(b, u.bbox.left + u.bbox.width);
        if (rr > l) ctx.fillRect(l, top, rr - l, h);
      }
      ctx.restore();
    };
  }

  function timePlot(el, spec) {
    // spec: t, ys, series (uPlot series options), yLabel, file, height
    const px = () => Math.max(100, Math.round(el.clientWidth || 600));
    const full = [spec.t[0], spec.t[spec.t.length - 1]];
    const data = decimate(spec.t, spec.ys, full[0], full[1], px());
    let lastRange = null;
    const u = make(el, {
      height: spec.height || 230,
      scales: {x: {time: false}},
      series: [{label: "t", value: (u, v) => v == null ? "—" : v.toFixed(3) + " s"}].concat(spec.series),
      axes: [Object.assign({label: "time [s]"}, AXIS), Object.assign({label: spec.yLabel, size: 60}, AXIS)],
      cursor: {sync: {key: "robid-time"}, drag: {x: true, y: false, setScale: true},
               bind: {dblclick: () => () => null}},  // the page's own double-click shows all
      hooks: {
        drawClear: [shadeHeldOut(spec.file)],
        draw: spec.draw ? [spec.draw] : [],
        setScale: [(u, key) => {
          if (key !== "x") return;
          const x0 = u.scales.x.min, x1 = u.scales.x.max;
          if (lastRange && lastRange[0] === x0 && lastRange[1] === x1) return;
          lastRange = [x0, x1];
          u.setData(decimate(spec.t, spec.ys, x0, x1, px()), false);
          shareZoom(u);
        }],
      },
    }, data);
    u.root.addEventListener("dblclick", () => zoomAll(null));
    timePlots.push({u: u, full: full, spec: spec, reset: () => { lastRange = null; }});
    return u;
  }

  function zoomAll(range) {
    syncing = true;
    for (const p of timePlots) { p.reset(); p.u.setScale("x", {min: (range || p.full)[0], max: (range || p.full)[1]}); }
    syncing = false;
  }

  function drawTorque(fileIdx) {
    for (const p of timePlots) { p.u.destroy(); plots.splice(plots.findIndex(q => q.u === p.u), 1); }
    timePlots.length = 0;
    const s = doc.series[fileIdx], file = doc.files[s.file];
    const floor = doc.noise_floor || [];
    for (const el of figs("measured-vs-model")) {
      el.innerHTML = "";
      try {
        const j = +el.dataset.joint, d = s.joints[j - 1], un = units(j).tau;
        const ys = [d.meas, d.model], series = [
          {label: "measured", stroke: C.meas, width: 1, value: (u, v) => fmt(v) + " " + un},
          {label: "model", stroke: C.model, width: 1.5, value: (u, v) => fmt(v) + " " + un}];
        if (d.cad) { ys.push(d.cad); series.push({label: "CAD", stroke: C.cad, width: 1.2, dash: [6, 4], value: (u, v) => fmt(v) + " " + un}); }
        timePlot(el, {t: s.t, ys: ys, series: series, yLabel: "torque [" + un + "]", file: file});
      } catch (e) { fail(el, e); }
    }
    for (const el of figs("residual")) {
      el.innerHTML = "";
      try {
        const j = +el.dataset.joint, d = s.joints[j - 1], un = units(j).tau;
        const raw = new Float32Array(d.meas.length);
        for (let i = 0; i < raw.length; i++) raw[i] = d.meas[i] - d.model[i];
        const nf = floor[j - 1];
        const ys = [raw, d.rf], series = [
          {label: "residual (raw)", stroke: C.raw, width: 1, value: (u, v) => fmt(v) + " " + un},
          {label: "residual (filtered)", stroke: C.resid, width: 1.5, value: (u, v) => fmt(v) + " " + un}];
        timePlot(el, {t: s.t, ys: ys, series: series, yLabel: "residual [" + un + "]", file: file, height: 170,
                      draw: nf ? u => hline(u, [nf, -nf], "rgba(0,0,0,0.45)", [3, 3]) : null});
      } catch (e) { fail(el, e); }
    }
  }

  function hline(u, values, color, dash) {
    const ctx = u.ctx;
    ctx.save();
    ctx.strokeStyle = color; ctx.lineWidth = 1; ctx.setLineDash(dash || []);
    for (const v of values) {
      const y = u.valToPos(v, "y", true);
      if (y < u.bbox.top || y > u.bbox.top + u.bbox.height) continue;
      ctx.beginPath(); ctx.moveTo(u.bbox.left, y); ctx.lineTo(u.bbox.left + u.bbox.width, y); ctx.stroke();
    }
    ctx.restore();
  }

  // ------------------------------------------------------------------ scatter and bars
  function scatter(el, spec) {
    // spec: groups [{x, y, color, label}], xLabel, yLabel, title; at most ~6000 points a group
    const data = [null], series = [{}];
    for (const g of spec.groups) {
      const step = Math.max(1, Math.ceil(g.x.length / (spec.max || 6000)));
      const xs = [], ys = [];
      for (let i = 0; i < g.x.length; i += step) {
        const a = g.x[i], b = g.y[i];
        if (a === a && b === b) { xs.push(a); ys.push(b); }
      }
      data.push([xs, ys]);
      series.push({label: g.label, stroke: g.color, fill: g.color, paths: uPlot.paths.points(),
                   points: {show: false}, facets: [{scale: "x", auto: true}, {scale: "y", auto: true}],
                   width: 0, pointSize: 2.2});
    }
    for (const s of series.slice(1)) s.points = {show: true, size: 2.6, width: 0, fill: s.fill, stroke: s.stroke};
    return make(el, {
      mode: 2, height: spec.height || 210, title: spec.title,
      legend: {show: spec.groups.length > 1, live: false},
      scales: {x: {time: false}},
      series: series,
      axes: [Object.assign({label: spec.xLabel, space: 35}, AXIS), Object.assign({label: spec.yLabel, size: 55}, AXIS)],
      cursor: {drag: {x: true, y: true}, points: {show: false}},
    }, data);
  }

  function bars(el, spec) {
    // spec: x, bars (heights), lines [{y, color, label, dash}], xLabel, yLabel, title
    const series = [{label: spec.xName || "x", value: (u, v) => fmt(v, 3)},
      {label: spec.barLabel, fill: spec.barColor || "rgba(31,119,180,0.55)", stroke: spec.barColor || "#1f77b4",
       width: 0, paths: uPlot.paths.bars({size: [spec.barWidth || 0.9, 40], gap: 0}), points: {show: false},
       value: (u, v) => fmt(v, 3)}];
    const data = [spec.x, spec.bars];
    for (const l of spec.lines || []) {
      series.push({label: l.label, stroke: l.color, width: 1.5, dash: l.dash, points: {show: false},
                   paths: l.smooth ? uPlot.paths.spline() : undefined, value: (u, v) => fmt(v, 3)});
      data.push(l.y);
    }
    const scales = {x: {time: false}, y: {}};
    if (spec.xRange) scales.x.range = () => spec.xRange;
    if (spec.yRange) scales.y.range = () => spec.yRange;
    return make(el, {
      height: spec.height || 210, title: spec.title, legend: {show: false}, scales: scales,
      series: series,
      axes: [Object.assign({label: spec.xLabel}, AXIS), Object.assign({label: spec.yLabel, size: 55}, AXIS)],
      cursor: {drag: {x: false, y: false}},
    }, data);
  }

  // ------------------------------------------------------------------ residual analysis
  function drawResidualAnalysis() {
    const rs = doc.residual_stats, s = doc.series[0];
    if (!rs || !s) return;
    for (const [name, key, sym] of [["residual-vs-q", "q", "q"], ["residual-vs-qd", "qd", "q̇"]]) {
      for (const el of figs(name)) {
        try {
          const j = +el.dataset.joint, d = s.joints[j - 1], un = units(j);
          scatter(el, {groups: [{x: d[key], y: d.rf, color: "rgba(31,119,180,0.4)", label: "rows"}],
                       title: "vs " + sym + j, xLabel: sym + j + " [" + un[key] + "]",
                       yLabel: "filtered residual [" + un.tau + "]"});
        } catch (e) { fail(el, e); }
      }
    }
    for (const el of figs("residual-histogram")) {
      try {
        const j = +el.dataset.joint, st = rs.joints[j - 1], un = units(j).tau;
        if (!st.n) { caption(el, "no " + rs.rows + " rows hold this joint's torque (partial logs)"); continue; }
        const e = st.hist.edges, w = e[1] - e[0], n = st.n;
        const x = [], dens = [], pdf = [];
        for (let i = 0; i < st.hist.counts.length; i++) {
          const c = 0.5 * (e[i] + e[i + 1]);
          x.push(c); dens.push(st.hist.counts[i] / (n * w));
          pdf.push(st.std > 0 ? Math.exp(-0.5 * ((c - st.mean) / st.std) ** 2) / (st.std * Math.sqrt(2 * Math.PI)) : null);
        }
        bars(el, {x: x, bars: dens, barLabel: "residual", barWidth: 1,
                  lines: [{y: pdf, color: C.resid, label: "normal", smooth: true}],
                  title: "histogram: σ " + fmt(st.std, 3) + " " + un,
                  xLabel: "raw residual [" + un + "]", yLabel: "density [1/" + un + "]"});
      } catch (e) { fail(el, e); }
    }
    const lags = [];
    for (let k = -rs.lags; k <= rs.lags; k++) lags.push(k * rs.lag_s);
    const band = lags.map(() => rs.band), nband = lags.map(() => -rs.band);
    const half = (rs.lags + 0.6) * rs.lag_s;
    for (const [name, key, title] of [["residual-acf", "acf", "autocorr."], ["residual-ccf", "ccf", "cross-corr. with q̇"]]) {
      for (const el of figs(name)) {
        try {
          const j = +el.dataset.joint, st = rs.joints[j - 1];
          if (!st.n) { caption(el, "no " + rs.rows + " rows hold this joint's torque (partial logs)"); continue; }
          const vals = st[key];
          const out = vals.filter((v, i) => Math.abs(v) > rs.band && !(key === "acf" && i === rs.lags)).length;
          const top = key === "acf" ? 1 : Math.min(1, 1.15 * Math.max(2 * rs.band, ...vals.map(Math.abs)));
          bars(el, {x: lags, bars: vals, barLabel: key, barWidth: 0.5, xRange: [-half, half], yRange: [-top, top],
                    barColor: out ? "#c0392b" : "#1f77b4",
                    lines: [{y: band, color: "#555", dash: [4, 3], label: "99 %"}, {y: nband, color: "#555", dash: [4, 3], label: "99 %"}],
                    title: title + (key === "ccf" ? j : "") + (out ? ": " + out + " lag(s) out" : ": white"),
                    xLabel: "lag [s]", yLabel: key === "acf" ? "autocorrelation" : "correlation"});
        } catch (e) { fail(el, e); }
      }
    }
  }

  // ------------------------------------------------------------------ diagnosis evidence
  function drawEvidence() {
    const dg = doc.diagnosis;
    if (!dg) return;
    for (const el of figs("evidence")) {
      try {
        const rank = +el.dataset.suggestion, sg = dg.suggestions[rank - 1], j = sg.joint;
        const ev = dg.evidence[String(j)], un = units(j);
        if (!ev) throw new Error("no residual rows for joint " + j);
        const panels = [["q", "q", "r2_q"], ["qd", "q̇", "r2_qd"], ["qdd", "q̈", "r2_qdd"]];
        for (const [key, sym, r2] of panels) {
          const box = document.createElement("div");
          box.className = "plot";
          el.appendChild(box);
          const strong = sg.strongest === key;
          scatter(box, {groups: [{x: ev[key], y: ev.r, color: strong ? "rgba(192,57,43,0.5)" : "rgba(31,119,180,0.4)", label: "rows"}],
                        title: (strong ? "▶ " : "") + "vs " + sym + j + (sg[r2] != null ? ": R² " + fmt(sg[r2], 3) : ""),
                        xLabel: sym + j + " [" + un[key] + "]", yLabel: "residual [" + un.tau + "]", height: 200});
        }
        if (sg.period) {  // a ripple: the residual folded on its period repeats
          const box = document.createElement("div");
          box.className = "plot";
          el.appendChild(box);
          const P = sg.period, x = new Float32Array(ev.q.length);
          for (let i = 0; i < x.length; i++) x[i] = ((ev.q[i] % P) + P) % P;
          scatter(box, {groups: [{x: x, y: ev.r, color: "rgba(192,57,43,0.5)", label: "rows"}],
                        title: "folded on " + fmt(P, 4) + " " + un.q + (sg.repeat != null ? ": repeats, r " + fmt(sg.repeat, 3) : ""),
                        xLabel: "q" + j + " mod " + fmt(P, 4) + " [" + un.q + "]", yLabel: "residual [" + un.tau + "]", height: 200});
        }
        el.dataset.drawn = "1";
      } catch (e) { fail(el, e); }
    }
  }

  // ------------------------------------------------------------------ error ladder
  function drawLadder() {
    const el = figs("ladder")[0];
    if (!el || !doc.ladder) return;
    try {
      const rungs = doc.ladder.rungs, x = rungs.map((r, i) => i + 1);
      const n = Math.max(0, ...rungs.map(r => r.rmse.length));
      const data = [x], series = [{label: "run", value: (u, v) => v == null ? "—" : "#" + v + " " + rungs[v - 1].label}];
      for (let j = 0; j < n; j++) {
        data.push(rungs.map(r => r.rmse[j] != null && r.rmse[j] > 0 ? r.rmse[j] : null));
        series.push({label: "J" + (j + 1), stroke: C.joints[j % C.joints.length], width: 2, spanGaps: true,
                     points: {show: true, size: 7}, value: (u, v) => fmt(v, 4) + " " + units(j + 1).tau});
      }
      const short = rungs.length > 6;
      make(el, {
        height: 300, scales: {x: {time: false, range: () => [0.6, rungs.length + 0.4]}, y: {distr: 3}},
        series: series,
        axes: [Object.assign({label: "run (model version)", size: 60,
                              splits: () => x,
                              values: (u, splits) => splits.map(i => { const r = rungs[i - 1]; if (!r) return ""; return (r.same_data ? "● " : "") + (short ? "#" + i + " v" + r.version : r.label.slice(0, 40)); })}, AXIS),
               Object.assign({label: "held-out RMSE [" + units(1).tau + "] (log)", size: 70}, AXIS)],
        cursor: {drag: {x: false, y: false}},
      }, data);
    } catch (e) { fail(el, e); }
  }

  // ------------------------------------------------------------------ Bode
  function drawBode() {
    if (!doc.bode) return;
    for (const el of figs("bode")) {
      try {
        const frf = doc.bode.frfs[+el.dataset.frf], cell = frf.cells[+el.dataset.cell];
        const joined = uPlot.join([[frf.f_hz, cell.mag], [frf.f_model, cell.mag_model]]);
        const joinedP = uPlot.join([[frf.f_hz, cell.phase], [frf.f_model, cell.phase_model]]);
        const fx = {time: false, distr: 3};
        const meas = (label, v) => ({label: label, stroke: "#c0392b", fill: "rgba(192,57,43,0.35)", width: 0,
                                     paths: () => null, points: {show: true, size: 7, width: 1.2}, value: v});
        const line = (label, v) => ({label: label, stroke: C.model, width: 2, spanGaps: true, points: {show: false}, value: v});
        const title = document.createElement("h4");
        title.textContent = cell.name + ": motor acceleration / motor torque";
        el.appendChild(title);
        const boxes = [0, 1, 2].map(() => { const b = document.createElement("div"); el.appendChild(b); return b; });
        const cursor = {sync: {key: "robid-bode-" + el.dataset.frf + "-" + el.dataset.cell}, drag: {x: false, y: false}};
        const fval = (u, v) => v == null ? "—" : fmt(v, 4) + " Hz";
        const mag = (u, v) => fmt(v, 3) + " rad/(N·m·s²)";
        const deg = (u, v) => fmt(v, 3) + "°";
        make(boxes[0], {height: 220, scales: {x: fx, y: {distr: 3}}, cursor: cursor,
          series: [{label: "f", value: fval}, meas("measured", mag), line("fitted model", mag)],
          axes: [Object.assign({label: "frequency [Hz]"}, AXIS), Object.assign({label: "|q̈m/τ| [rad/(N·m·s²)]", size: 70}, AXIS)]}, joined);
        make(boxes[1], {height: 170, scales: {x: fx}, cursor: cursor,
          series: [{label: "f", value: fval}, meas("measured", deg), line("model", deg)],
          axes: [Object.assign({label: "frequency [Hz]"}, AXIS), Object.assign({label: "phase [deg]", size: 70}, AXIS)]}, joinedP);
        make(boxes[2], {height: 130, scales: {x: fx, y: {range: () => [0, 1.05]}}, cursor: cursor,
          series: [{label: "f", value: fval}, meas("coherence", (u, v) => fmt(v, 3))],
          axes: [Object.assign({label: "frequency [Hz]"}, AXIS), Object.assign({label: "coherence", size: 70}, AXIS)]},
          [frf.f_hz, frf.coherence]);
        el.dataset.drawn = "1";
      } catch (e) { fail(el, e); }
    }
  }

  // ------------------------------------------------------------------ tracking over time
  function drawTrackingTrace() {
    const tr = doc.tracking && doc.tracking.trace;
    if (!tr) return;
    const names = {before: "before (CAD model)", after: "after (identified set)", check: "check run"};
    const colors = {before: "#9aa5b8", after: "#1f77b4", check: "#6a51a3"};
    for (const el of figs("tracking-trace")) {
      try {
        const phases = ["before", "after", "check"].filter(p => tr[p]);
        const mm = (u, v) => fmt(v, 3) + " mm";
        make(el, {height: 240, scales: {x: {time: false}},
          series: [{label: "t", value: (u, v) => v == null ? "—" : fmt(v, 4) + " s"},
                   ...phases.map(p => ({label: names[p], stroke: colors[p], width: 1.5, value: mm}))],
          axes: [Object.assign({label: "time along the path [s]"}, AXIS),
                 Object.assign({label: "tool position error [mm]", size: 70}, AXIS)],
          cursor: {drag: {x: true, y: false}}}, [tr.t, ...phases.map(p => tr[p])]);
      } catch (e) { fail(el, e); }
    }
  }

  // ------------------------------------------------------------------ robot drawing
  function drawRobot() {
    const svg = figs("robot")[0], dr = doc.robot.drawing;
    if (!svg || !dr) return;
    const NS = "http://www.w3.org/2000/svg";
    const W = 520, H = 440;
    let yaw = -0.6, pitch = 0.45;
    const pts = dr.points;
    const span = Math.max(1e-3, ...[0, 1, 2].map(k => Math.max(...pts.map(p => p[k])) - Math.min(...pts.map(p => p[k]))));
    const ctr = [0, 1, 2].map(k => pts.reduce((s, p) => s + p[k], 0) / pts.length);
    function proj(p) {  // turn about z (yaw), tilt (pitch); screen: x right, z up
      const x = p[0] - ctr[0], y = p[1] - ctr[1], z = p[2] - ctr[2];
      const xr = x * Math.cos(yaw) - y * Math.sin(yaw), yr = x * Math.sin(yaw) + y * Math.cos(yaw);
      const zs = z * Math.cos(pitch) - yr * Math.sin(pitch);
      const s = 0.62 * Math.min(W, H) / span;
      return [W / 2 + s * xr, H / 2 - s * zs];
    }
    function el(name, attrs, text) {
      const e = document.createElementNS(NS, name);
      for (const k in attrs) e.setAttribute(k, attrs[k]);
      if (text != null) e.textContent = text;
      svg.appendChild(e);
      return e;
    }
    function arrow(a, b, color, w) {
      const p = proj(a), q = proj(b);
      el("line", {x1: p[0], y1: p[1], x2: q[0], y2: q[1], stroke: color, "stroke-width": w, "marker-end": "url(#head-" + color.slice(1) + ")"});
    }
    function draw() {
      svg.innerHTML = "";
      const defs = el("defs", {});
      for (const c of ["#d62728", "#2ca02c", "#222222"]) {
        const m = document.createElementNS(NS, "marker");
        for (const [k, v] of Object.entries({id: "head-" + c.slice(1), viewBox: "0 0 10 10", refX: 8, refY: 5, markerWidth: 5, markerHeight: 5, orient: "auto-start-reverse"})) m.setAttribute(k, v);
        const path = document.createElementNS(NS, "path");
        path.setAttribute("d", "M 0 0 L 10 5 L 0 10 z"); path.setAttribute("fill", c);
        m.appendChild(path); defs.appendChild(m);
      }
      // floor grid at the base, 0.1·span apart
      const g = 0.25 * span, z0 = 0;
      for (let k = -2; k <= 2; k++) {
        const a = proj([k * g, -2 * g, z0]), b = proj([k * g, 2 * g, z0]), c = proj([-2 * g, k * g, z0]), d = proj([2 * g, k * g, z0]);
        el("line", {x1: a[0], y1: a[1], x2: b[0], y2: b[1], stroke: "#e3e7ee"});
        el("line", {x1: c[0], y1: c[1], x2: d[0], y2: d[1], stroke: "#e3e7ee"});
      }
      for (let k = 1; k < pts.length; k++) {
        const a = proj(pts[dr.parents[k - 1]] || pts[0]), b = proj(pts[k]);
        el("line", {x1: a[0], y1: a[1], x2: b[0], y2: b[1], stroke: "#8a94a6", "stroke-width": 7, "stroke-linecap": "round"});
      }
      for (let j = 0; j < dr.axes.length; j++) {
        const o = pts[j + 1], ax = dr.axes[j], L = 0.13 * span;
        const type = (doc.robot.joints[j] || {}).type;
        arrow(o, [o[0] + L * ax[0], o[1] + L * ax[1], o[2] + L * ax[2]], type === "prismatic" ? "#2ca02c" : "#d62728", 2.5);
      }
      const labels = [];  // joints at one place (a wrist) share one label
      for (let k = 0; k < pts.length; k++) {
        const same = labels.find(l => Math.hypot(...[0, 1, 2].map(i => l.at[i] - pts[k][i])) < 1e-6 * span);
        if (same && k) { same.text += "," + k; continue; }
        labels.push({at: pts[k], text: k ? String(k) : "base"});
      }
      const placed = [];  // labels whose points are close on screen go one line lower
      for (const l of labels) {
        const p = proj(l.at);
        el("circle", {cx: p[0], cy: p[1], r: l.text === "base" ? 7 : 5, fill: l.text === "base" ? "#50607a" : "#1d2330"});
        let y = p[1] - 6;
        while (placed.some(q => Math.abs(q[0] - p[0]) < 30 && Math.abs(q[1] - y) < 13)) y += 14;
        placed.push([p[0], y]);
        el("text", {x: p[0] + 8, y: y, "font-size": 13, "font-weight": 600}, l.text);
      }
      const gn = Math.hypot(...dr.gravity);
      if (gn > 0) {
        const o = [ctr[0] + 0.42 * span, ctr[1], ctr[2] + 0.3 * span], L = 0.18 * span;
        arrow(o, [o[0] + L * dr.gravity[0] / gn, o[1] + L * dr.gravity[1] / gn, o[2] + L * dr.gravity[2] / gn], "#222222", 2);
      }
      // scale bar
      const s = 0.62 * Math.min(W, H) / span, nice = Math.pow(10, Math.floor(Math.log10(span / 2)));
      const len = (span / 2 >= 5 * nice ? 5 : span / 2 >= 2 * nice ? 2 : 1) * nice;
      el("line", {x1: 20, y1: H - 20, x2: 20 + s * len, y2: H - 20, stroke: "#1d2330", "stroke-width": 2});
      el("text", {x: 20, y: H - 26, "font-size": 12}, fmt(len, 3) + " m");
    }
    let drag = null;
    svg.addEventListener("pointerdown", e => { drag = [e.clientX, e.clientY, yaw, pitch]; svg.setPointerCapture(e.pointerId); });
    svg.addEventListener("pointermove", e => {
      if (!drag) return;
      yaw = drag[2] + (e.clientX - drag[0]) * 0.01;
      pitch = Math.max(-1.4, Math.min(1.4, drag[3] + (e.clientY - drag[1]) * 0.01));
      draw();
    });
    svg.addEventListener("pointerup", () => { drag = null; });
    draw();
    svg.dataset.drawn = "1";
  }

  // ------------------------------------------------------------------ page
  function wire() {
    for (const b of document.querySelectorAll("button.copy")) {
      b.addEventListener("click", () => {
        const text = b.dataset.copy;
        (navigator.clipboard ? navigator.clipboard.writeText(text) : Promise.reject()).then(
          () => { b.textContent = "copied"; },
          () => { const r = document.createRange(); r.selectNodeContents(b.previousElementSibling); getSelection().removeAllRanges(); getSelection().addRange(r); });
      });
    }
    const reset = document.getElementById("zoom-reset");
    if (reset) reset.addEventListener("click", () => zoomAll(null));
    const sel = document.getElementById("file-select");
    if (sel) sel.addEventListener("change", () => drawTorque(+sel.value));
    let timer = null;
    window.addEventListener("resize", () => {
      clearTimeout(timer);
      timer = setTimeout(() => { for (const p of plots) p.u.setSize({width: width(p.el), height: p.h || p.u.height}); }, 150);
    });
  }

  async function main() {
    await unpackAll(doc);
    const steps = [() => doc.series && doc.series.length && drawTorque(0), drawResidualAnalysis, drawEvidence, drawLadder, drawBode, drawTrackingTrace, drawRobot];
    for (const step of steps) {
      try { step(); } catch (e) { console.error("robid report: " + e); }
    }
    wire();
    // renderMs: this script's own work; readyMs: since navigation start (the first render)
    window.robidReport = {doc: doc, plots: plots, timePlots: timePlots, zoomAll: zoomAll,
                          renderMs: performance.now() - t0, readyMs: performance.now()};
    document.body.dataset.rendered = "1";
  }

  main().catch(e => { console.error("robid report: " + e); document.body.dataset.rendered = "error"; });
})();
