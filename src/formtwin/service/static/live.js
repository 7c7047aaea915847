// formtwin live page: Server-Sent Events -> uPlot charts. No build step, no dependencies
// beyond uPlot (shipped beside this file, MIT licence in uPlot.LICENSE).
"use strict";
(function () {
  const WINDOW = 500;            // points kept per chart
  const charts = [];             // {key, plot, data: [x, lo, mid, hi, (extra)]}
  let nPoints = 0;

  function el(id) { return document.getElementById(id); }

  function makeChart(title, key, opts) {
    const box = document.createElement("div");
    box.className = "panel";
    box.dataset.key = key;
    const h = document.createElement("h2");
    h.textContent = title;
    const latest = document.createElement("span");
    latest.className = "latest";
    h.appendChild(latest);
    box.appendChild(h);
    el("grid").appendChild(box);
    const series = [{label: "product"}].concat(opts.series);
    const plot = new uPlot({
      width: Math.max(280, box.clientWidth - 10), height: 150, series: series, bands: opts.bands || [],
      legend: {show: false},
      scales: {x: {time: false}, y: opts.yRange ? {range: opts.yRange} : {}},
      axes: [{size: 24}, {size: 62}],
    }, opts.series.map(() => []).concat([[]]), box);
    const c = {key: key, plot: plot, data: [[]].concat(opts.series.map(() => [])),
               extract: opts.extract, latest: latest, label: opts.label};
    charts.push(c);
    return c;
  }

  function band(color) {
    return [
      {label: "-3s", stroke: "transparent", points: {show: false}},
      {label: "mean", stroke: color, width: 1.5, points: {show: false}},
      {label: "+3s", stroke: "transparent", points: {show: false}},
    ];
  }

  function fmt(v) {
    if (v === null || v === undefined) return "-";
    const a = Math.abs(v);
    return (a !== 0 && (a < 1e-3 || a >= 1e5)) ? v.toExponential(3) : v.toPrecision(4);
  }

  // the line's sensors: their last values, and the camera's measured final angle against
  // the prediction and 90 % interval issued for its product (x: the product's index)
  let finalChart = null;
  function buildSensors(sensors) {
    el("sensor-values").hidden = false;
    finalChart = makeChart("final angle (deg): camera vs predicted, calibrated 90 % interval",
                           "final", {
      series: [
        {label: "lo90", stroke: "transparent", points: {show: false}},
        {label: "predicted", stroke: "#b5561b", width: 1.5, points: {show: false}},
        {label: "hi90", stroke: "transparent", points: {show: false}},
        {label: "camera", stroke: "#222", width: 0, points: {show: true, size: 4}},
      ],
      bands: [{series: [3, 1], fill: "rgba(181,86,27,0.18)"}],
      extract: null,
    });
    finalChart.sensorFed = true;
    el("sensor-values").dataset.sensors = sensors.join(",");
  }

  function addSensor(e, charted) {
    lastValues[e.sensor] = e;
    el("sensor-values").textContent = "sensors, last values: " + Object.keys(lastValues)
      .sort().map((k) => {
        const v = lastValues[k];
        return k + " " + fmt(v.value) + " (" + v.part_id + ", " + v.status + ")";
      }).join("   ");
    if (!charted || e.redelivered || !finalChart || e.predicted_deg === null || e.predicted_deg === undefined ||
        e.status === "held" || !e.interval90_deg) return;
    const d = finalChart.data;
    let i = d[0].length;
    while (i > 0 && d[0][i - 1] > e.index) i -= 1;  // out of order: keep x ascending
    [e.index, e.interval90_deg[0], e.predicted_deg, e.interval90_deg[1], e.value]
      .forEach((y, k) => d[k].splice(i, 0, y));
    if (d[0].length > WINDOW) d.forEach((col) => col.shift());
    finalChart.latest.textContent = "  " + fmt(e.value) + " measured, " +
      fmt(e.predicted_deg) + " predicted";
    document.body.dataset.finals = String(d[0].length);
  }
  let lastValues = {};

  function build(names, units, nParticles, outputs, sensors) {
    el("grid").innerHTML = "";
    charts.length = 0;
    names.forEach((name) => {
      const unit = units && units[name] ? " [" + units[name] + "]" : "";
      makeChart(name + unit, name, {
        series: band("#1f5fa8"), bands: [{series: [3, 1], fill: "rgba(31,95,168,0.18)"}],
        extract: (p) => {
          const m = p.mean[name], s = p.std[name];
          if (m === null || s === null) return [null, null, null];
          return [m - 3 * s, m, m + 3 * s];
        },
      });
    });
    (outputs || []).forEach((o, k) => {
      makeChart(o.label + " (" + o.unit + "): predicted, measured", "angle" + k, {
        series: band("#b5561b").concat([{label: "measured", stroke: "#222", width: 0,
                                         points: {show: true, size: 3}}]),
        bands: [{series: [3, 1], fill: "rgba(181,86,27,0.18)"}],
        extract: (p) => {
          const m = p.angles_mean[k], s = p.angles_std[k];
          const meas = p.measured_angles ? p.measured_angles[k] : null;
          if (m === null || s === null) return [null, null, null, meas];
          return [m - 3 * s, m, m + 3 * s, meas];
        },
      });
    });
    if (sensors && sensors.length) buildSensors(sensors);
    // a fixed axis 0 .. N: an ESS of 1 of 500 must look like one, not like a flat "1, 1, 1"
    makeChart("effective sample size" + (nParticles ? " (of N = " + nParticles + ")" : ""),
              "ess", {
      series: [{label: "ESS", stroke: "#2a7a2a", width: 1.5, points: {show: false}}],
      yRange: nParticles ? [0, nParticles] : null,
      extract: (p) => [p.ess],
      label: (ys) => fmt(ys[0]),
    });
  }

  // control charts: one per monitored quantity (EWMA of the standardised residual with its
  // limits; the health statistics' mismatch CUSUM with its decision interval), a GLR chart
  // (level change, log-likelihood ratio and its limit) per state variable, alarms as red
  // points
  const TITLES = {ewma: "EWMA chart: ", mismatch: "model-mismatch CUSUM: ",
                  glr: "GLR chart (level change): "};
  function buildMonitor(mon) {
    if (!mon) return;
    const charted = mon.quantities.map((n) => [n, "ewma"]).concat(
      mon.health.map((n) => [n, "mismatch"]), (mon.glr || []).map((n) => [n, "glr"]));
    charted.forEach(([name, chart]) => {
      const title = TITLES[chart] + name +
        (chart === "glr" ? " (log-likelihood ratio)" : " (sigma units)");
      makeChart(title, (chart === "glr" ? "glr:" : "chart:") + name, {
        series: [
          {label: "statistic", stroke: "#444", width: 1.2, points: {show: false}},
          {label: "upper limit", stroke: "#c33", width: 1, dash: [4, 3], points: {show: false}},
          {label: "lower limit", stroke: "#c33", width: 1, dash: [4, 3], points: {show: false}},
          {label: "alarm", stroke: "#d00", width: 0, points: {show: true, size: 7, fill: "#d00"}},
        ],
        extract: (p) => {
          const m = p.monitoring;
          const c = m && m.charts && m.charts[name] ? m.charts[name][chart] : null;
          if (!c) return [null, null, null, null];
          const raised = (m.alarms || []).some(
            (a) => a.variable === name && (chart !== "glr" || a.chart === "glr"));
          return [c[0], c[1], chart === "ewma" ? -c[1] : null, raised ? c[0] : null];
        },
        label: (ys) => fmt(ys[0]) + " (limit " + fmt(ys[1]) + ")",
      });
    });
  }

  // alarm episodes: one per chart and variable from its first signal until the chart has
  // been quiet for its clear-after products; acknowledged per episode
  const alarmRows = new Map();
  const token = new URLSearchParams(window.location.search).get("token") || "";
  function showAlarm(a) {
    let row = alarmRows.get(a.id);
    if (!row) {
      row = document.createElement("div");
      row.className = "alarm";
      row.dataset.id = String(a.id);
      el("alarms").prepend(row);
      alarmRows.set(a.id, row);
    }
    row.innerHTML = "";
    row.dataset.state = a.state;
    row.classList.toggle("cleared", a.state !== "active");
    const text = document.createElement("span");
    const span = a.last_seq > a.raised_seq ? " to " + a.last_seq : "";
    text.textContent = "#" + a.id + " " + a.variable + " " + a.chart + " " + a.side + ": " +
      a.state + (a.cleared_seq ? " at product " + a.cleared_seq : "") + "; raised at product " +
      a.raised_seq + " (" + a.raised_part + "), " + a.signals + " signal" +
      (a.signals === 1 ? "" : "s") + " (products " + a.raised_seq + span + "), largest " +
      fmt(a.statistic) + " beyond " + fmt(a.limit);
    row.appendChild(text);
    if (a.acked_at) {
      row.classList.add("acked");
      const s = document.createElement("span");
      s.textContent = "; acknowledged";
      row.appendChild(s);
    } else {
      const b = document.createElement("button");
      b.textContent = "acknowledge";
      b.onclick = () => {
        fetch("/api/alarms/" + a.id + "/ack", {method: "POST",
          headers: {"X-Formtwin-Token": token, "Content-Type": "application/json"},
          body: JSON.stringify({note: "acknowledged on the live page"})})
          .then((r) => r.json().then((j) => {
            if (r.ok) showAlarm(j); else el("alarm-error").textContent = j.error || r.status;
          }));
      };
      row.appendChild(b);
    }
    let unacked = 0, active = 0;
    alarmRows.forEach((r) => {
      if (!r.classList.contains("acked")) unacked += 1;
      if (r.dataset.state === "active") active += 1;
    });
    el("n-alarms").textContent = String(unacked);
    el("n-active").textContent = String(active);
    document.body.dataset.alarms = String(alarmRows.size);
    document.body.dataset.openAlarms = String(unacked);
    document.body.dataset.activeAlarms = String(active);
  }

  function loadAlarms() {
    return fetch("/api/alarms").then((r) => r.ok ? r.json() : []).then((list) => {
      el("alarms").innerHTML = "";
      alarmRows.clear();
      list.forEach(showAlarm);
    });
  }

  // model health: a banner in words while the model does not explain the curves
  function showHealth(h) {
    const banner = el("banner");
    const mismatch = !!h && h.state === "model_mismatch";
    document.body.classList.toggle("mismatch", mismatch);
    document.body.dataset.health = mismatch ? "model_mismatch" : "ok";
    if (!mismatch) { banner.hidden = true; banner.innerHTML = ""; return; }
    const ep = h.episode || {};
    banner.innerHTML = "";
    const t = document.createElement("h2");
    t.textContent = "Model mismatch" + (ep.opened_seq ? " since product " + ep.opened_seq : "") +
      ": the model does not explain the force curves. The estimates below are not " +
      "supported by the data (marked model_mismatch); do not use them.";
    banner.appendChild(t);
    [["Expected", ep.expected], ["Seen", ep.seen]].forEach(([k, v]) => {
      if (!v) return;
      const d = document.createElement("div");
      d.textContent = k + ": " + v + ".";
      banner.appendChild(d);
    });
    if (ep.likely_causes) {
      const d = document.createElement("div");
      d.textContent = "Likely causes:";
      const ul = document.createElement("ul");
      ep.likely_causes.forEach((c) => {
        const li = document.createElement("li");
        li.textContent = c;
        ul.appendChild(li);
      });
      d.appendChild(ul);
      banner.appendChild(d);
    }
    banner.hidden = false;
  }

  function addPoint(p) {
    const x = p.seq !== null && p.seq !== undefined ? p.seq : nPoints;
    charts.forEach((c) => {
      if (c.sensorFed) return;
      const ys = c.extract(p);
      c.data[0].push(x);
      ys.forEach((y, i) => c.data[i + 1].push(y));
      if (c.label) {
        if (ys[0] !== null) c.latest.textContent = "  " + c.label(ys);
      } else if (ys.length >= 3 && ys[1] !== null) {
        c.latest.textContent = "  " + fmt(ys[1]) + " (std " + fmt((ys[2] - ys[1]) / 3) + ")";
      }
      if (c.data[0].length > WINDOW) c.data.forEach((col) => col.shift());
    });
    nPoints += 1;
    el("last-part").textContent = p.part_id;
  }

  function redraw() {
    charts.forEach((c) => c.plot.setData(c.data));
    el("n-points").textContent = String(nPoints);
    document.body.dataset.points = String(nPoints);
  }

  function showCounts(counts, reasons) {
    if (!counts) return;
    ["accepted", "redelivered", "gated", "rejected"].forEach((k) => {
      el("n-" + k).textContent = String(counts[k] || 0);
    });
    if (reasons) {
      el("reasons").textContent = Object.keys(reasons).sort()
        .map((r) => r + ": " + reasons[r]).join("   ");
    }
  }

  let dirty = false;
  function schedule() {
    if (dirty) return;
    dirty = true;
    requestAnimationFrame(() => { dirty = false; redraw(); });
  }

  let source = null;
  function start() {
    Promise.all([fetch("/api/state").then((r) => r.json()),
                 fetch("/api/monitor").then((r) => r.ok ? r.json() : null)]).then(([st, mon]) => {
      nPoints = 0;
      finalChart = null;
      lastValues = {};
      build(st.names, st.units, st.n_particles, st.outputs, st.sensors);
      showHealth(st.health);
      buildMonitor(mon);
      if (mon) loadAlarms();
      st.points.forEach(addPoint);
      (st.finals || []).forEach((e) => addSensor(e, true));
      Object.values(st.last_values || {}).forEach((e) => addSensor(e, false));
      redraw();
      showCounts(st.counts, st.reasons);
      source = new EventSource("/events?last=" + st.last + "&epoch=" + st.epoch);
      source.onopen = () => { el("conn").textContent = "live"; };
      source.onerror = () => { el("conn").textContent = "reconnecting"; };
      source.onmessage = (ev) => {
        const e = JSON.parse(ev.data);
        if (e.type === "reset") {   // the service restarted: reload its state
          source.close();
          document.body.dataset.resets = String(Number(document.body.dataset.resets || 0) + 1);
          start();
          return;
        }
        if (e.type === "point") { addPoint(e); schedule(); }
        if (e.type === "sensor") { addSensor(e, true); schedule(); }
        if (e.type === "alarms") e.alarms.forEach(showAlarm);
        if (e.type === "health") showHealth(e.health);
        if (e.type === "ack") showAlarm(e.alarm);
        showCounts(e.counts, e.reasons);
      };
    }).catch(() => {
      el("conn").textContent = "retrying";
      setTimeout(start, 1000);
    });
  }
  start();
  window.addEventListener("resize", () => {
    charts.forEach((c) => {
      const w = Math.max(280, c.plot.root.parentNode.clientWidth - 10);
      c.plot.setSize({width: w, height: 150});
    });
  });
  window.formtwinLive = {points: () => nPoints, charts: charts};
})();
