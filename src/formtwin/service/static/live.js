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
      legend: {show: false}, scales: {x: {time: false}},
      axes: [{size: 24}, {size: 62}],
    }, opts.series.map(() => []).concat([[]]), box);
    const c = {key: key, plot: plot, data: [[]].concat(opts.series.map(() => [])),
               extract: opts.extract, latest: latest};
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

  function build(names, units) {
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
    [0, 1].forEach((k) => {
      makeChart("angle after stage " + (k + 1) + " (deg): predicted, measured", "angle" + k, {
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
    makeChart("effective sample size", "ess", {
      series: [{label: "ESS", stroke: "#2a7a2a", width: 1.5, points: {show: false}}],
      extract: (p) => [p.ess],
    });
  }

  function addPoint(p) {
    const x = p.seq !== null && p.seq !== undefined ? p.seq : nPoints;
    charts.forEach((c) => {
      const ys = c.extract(p);
      c.data[0].push(x);
      ys.forEach((y, i) => c.data[i + 1].push(y));
      if (ys.length >= 3 && ys[1] !== null) {
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
    fetch("/api/state").then((r) => r.json()).then((st) => {
      nPoints = 0;
      build(st.names, st.units);
      st.points.forEach(addPoint);
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
