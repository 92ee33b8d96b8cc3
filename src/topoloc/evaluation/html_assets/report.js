// topoloc HTML report: PR curves, threshold control, similarity matrix and query browser.
// Self-contained: every number and image comes from the JSON in #data.
(function () {
  "use strict";
  const errors = document.getElementById("errors");
  window.addEventListener("error", function (ev) {
    errors.hidden = false;
    errors.textContent += "script error: " + ev.message + "\n";
  });
  const D = JSON.parse(document.getElementById("data").textContent);
  const COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf",
                  "#7f7f7f", "#bcbd22"];
  const PAGE = 60;

  function el(tag, attrs, children) {
    const e = document.createElement(tag);
    for (const k in attrs || {}) {
      if (k === "text") e.textContent = attrs[k];
      else if (k === "cls") e.className = attrs[k];
      else e.setAttribute(k, attrs[k]);
    }
    (children || []).forEach(function (c) { if (c) e.appendChild(c); });
    return e;
  }
  function fmt(x, d) { return (x === null || x === undefined || !isFinite(x)) ? String(x) : Number(x).toFixed(d); }
  // Scores at the precision they have (whole numbers without decimals: run.decimals from the page's data).
  function score(run, x) { return fmt(x, run.decimals); }

  // ---- per-run statistics at a threshold (the metrics of docs/protocol.md) ----
  // A verified run accepts as localize accepts on a calibrated map (maps.calibration.accepts): a verified answer
  // whose confidence reaches the threshold; an unverified one at no threshold.
  function accepted(run, j, thr) { return run.score[j] >= thr && (!run.verified || run.verified[j]); }
  function stats(run, thr) {
    let tp = 0, fp = 0, rej = 0;
    for (let j = 0; j < run.score.length; j++) {
      if (accepted(run, j, thr)) { if (run.right[j]) tp++; else fp++; } else rej++;
    }
    return {tp: tp, fp: fp, rejected: rej, accepted: tp + fp,
            precision: tp + fp > 0 ? tp / (tp + fp) : 1, recall: tp / Math.max(run.n_pos, 1)};
  }
  function status(run, j, thr) {
    if (!accepted(run, j, thr)) return "rejected";
    return run.right[j] ? "correct" : "wrong";
  }

  // ---- PR curves of every run, with each run's current operating point ----
  const pr = document.getElementById("pr");
  const legend = document.getElementById("pr-legend");
  // The slider opens at the calibrated threshold of the map the run scored, else at the best F1.
  const states = D.runs.map(function (run) {
    const t = Array.from(new Set(run.score)).sort(function (a, b) { return a - b; });
    if (run.calibrated !== null && run.calibrated !== undefined) {
      let i = 0;
      while (i < t.length && t[i] < run.calibrated) i++;
      return {thresholds: t, index: i, filter: "all", shown: PAGE, view: "rank",
              opened: "the map's calibrated threshold " + fmt(run.calibrated, run.decimals)};
    }
    let best = 0, bestF = -1;
    t.forEach(function (thr, i) {
      const s = stats(run, thr);
      const f = s.precision + s.recall > 0 ? 2 * s.precision * s.recall / (s.precision + s.recall) : 0;
      if (f > bestF) { bestF = f; best = i; }
    });
    return {thresholds: t, index: best, filter: "all", shown: PAGE, view: "rank",
            opened: "the best F1, " + fmt(Math.max(bestF, 0), 3) + " (" +
                    (run.calibration_note || "the run scored no calibrated map") + ")"};
  });
  function thrOf(k) {
    const st = states[k];
    return st.index >= st.thresholds.length ? Infinity : st.thresholds[st.index];
  }

  function drawPR() {
    const ctx = pr.getContext("2d");
    const W = pr.width, H = pr.height, L = 48, B = 36, T = 10, R = 12;
    const X = function (r) { return L + r * (W - L - R); };
    const Y = function (p) { return H - B - p * (H - B - T); };
    ctx.clearRect(0, 0, W, H);
    ctx.strokeStyle = "#ddd"; ctx.fillStyle = "#444"; ctx.font = "11px sans-serif"; ctx.lineWidth = 1;
    for (let i = 0; i <= 10; i++) {
      const v = i / 10;
      ctx.beginPath(); ctx.moveTo(X(v), Y(0)); ctx.lineTo(X(v), Y(1)); ctx.stroke();
      ctx.beginPath(); ctx.moveTo(X(0), Y(v)); ctx.lineTo(X(1), Y(v)); ctx.stroke();
      if (i % 2 === 0) {
        ctx.textAlign = "center"; ctx.fillText(v.toFixed(1), X(v), H - B + 14);
        ctx.textAlign = "right"; ctx.fillText(v.toFixed(1), L - 4, Y(v) + 4);
      }
    }
    ctx.textAlign = "center"; ctx.fillText("recall", X(0.5), H - 6);
    ctx.save(); ctx.translate(12, Y(0.5)); ctx.rotate(-Math.PI / 2); ctx.fillText("precision", 0, 0); ctx.restore();
    D.runs.forEach(function (run, k) {
      ctx.strokeStyle = COLORS[k % COLORS.length]; ctx.lineWidth = 1.8; ctx.beginPath();
      run.pr.forEach(function (pt, i) { if (i === 0) ctx.moveTo(X(pt[0]), Y(pt[1])); else ctx.lineTo(X(pt[0]), Y(pt[1])); });
      ctx.stroke();
      const s = stats(run, thrOf(k));
      ctx.fillStyle = COLORS[k % COLORS.length];
      ctx.beginPath(); ctx.arc(X(s.recall), Y(s.precision), 5, 0, 2 * Math.PI); ctx.fill();
    });
  }
  D.runs.forEach(function (run, k) {
    legend.appendChild(el("div", {}, [el("span", {cls: "sw", style: "background:" + COLORS[k % COLORS.length]}),
      el("a", {href: "#run" + k, text: (k + 1) + ". " + run.label + " (AUC " + fmt(run.auc, 3) + ")"})]));
  });
  legend.appendChild(el("div", {text: "Dots: each run's precision and recall at its threshold below."}));

  // ---- similarity matrix with ground truth and the accepted best matches ----
  function drawMatrix(k) {
    const run = D.runs[k], c = document.getElementById("matrix" + k), img = c._imgs[states[k].view];
    if (!img || !img.complete) return;
    const ctx = c.getContext("2d"), W = c.width, H = c.height;
    const cw = W / run.n_queries, ch = H / run.n_places;
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(img, 0, 0, W, H);
    ctx.fillStyle = "rgba(255,255,255,0.55)";
    for (let i = 0; i < run.gt_rows.length; i++) {
      ctx.fillRect(run.gt_cols[i] * cw, run.gt_rows[i] * ch, Math.max(cw, 1), Math.max(ch, 1));
    }
    const thr = thrOf(k), r = Math.max(2, Math.min(4, cw));
    for (let j = 0; j < run.n_queries; j++) {
      const st = status(run, j, thr);
      if (st === "rejected") continue;
      ctx.fillStyle = st === "correct" ? "#2ca02c" : "#ff2020";
      ctx.beginPath(); ctx.arc((j + 0.5) * cw, (run.best_row[j] + 0.5) * ch, r, 0, 2 * Math.PI); ctx.fill();
    }
  }

  // ---- the query browser ----
  function figure(thumb, lines) {
    const src = thumb ? D.thumbs[thumb] : null;
    const pic = src ? el("img", {src: src, alt: lines[0]}) : el("div", {cls: "noimg", text: "no image"});
    return el("figure", {}, [pic, el("figcaption", {}, lines.map(function (t, i) {
      return el(i === 0 ? "b" : "div", {text: t});
    }))]);
  }
  // The inlier matches of a verified answer: the query and the map image side by side, one line a match.
  function matchesView(q, m) {
    const W = 180, gap = 8, hq = W * m.aspect[0], hm = W * m.aspect[1], H = Math.max(hq, hm);
    const ns = "http://www.w3.org/2000/svg", svg = document.createElementNS(ns, "svg");
    svg.setAttribute("width", 2 * W + gap); svg.setAttribute("height", H); svg.setAttribute("class", "matches");
    [[q.img, 0, hq], [m.img, W + gap, hm]].forEach(function (p) {
      if (!p[0] || !D.thumbs[p[0]]) return;
      const im = document.createElementNS(ns, "image");
      im.setAttribute("href", D.thumbs[p[0]]); im.setAttribute("x", p[1]); im.setAttribute("y", 0);
      im.setAttribute("width", W); im.setAttribute("height", p[2]); svg.appendChild(im);
    });
    m.xy.forEach(function (r) {
      const ln = document.createElementNS(ns, "line");
      ln.setAttribute("x1", r[0] * W); ln.setAttribute("y1", r[1] * hq);
      ln.setAttribute("x2", W + gap + r[2] * W); ln.setAttribute("y2", r[3] * hm); svg.appendChild(ln);
    });
    return svg;
  }
  function checkLine(it) {
    if (!it.check) return [];
    const c = it.check, conf = c.confidence === undefined ? "" : " · confidence " + fmt(c.confidence, 2);
    const parts = [el("span", {cls: "badge " + (c.verified ? "verified" : "unverified"),
                               text: (c.verified ? "verified" : "not verified") + " · " + c.inliers +
                                     " supporting inliers" + conf})];
    if (c.match) {
      const box = el("div", {cls: "matchbox"}), btn = el("button", {text: "inlier matches (" + c.match.file + ")"});
      btn.addEventListener("click", function () {
        if (box.firstChild) { box.textContent = ""; return; }
        box.appendChild(matchesView(it.q, c.match));
      });
      parts.push(btn, box);
    }
    return [el("div", {cls: "check"}, parts)];
  }
  function card(run, j, thr) {
    const it = run.items[j], st = status(run, j, thr);
    const q = it.q, b = it.best, c = it.correct;
    const head = el("div", {}, [
      el("span", {cls: "badge " + st, text: st}),
      el("span", {text: "  query " + j + (q.file ? " · " + q.file : "") + (q.time ? " · " + q.time : "") +
                        " · " + run.score_name + " " + score(run, run.score[j]) +
                        (run.has_pos[j] ? " · correct place at rank " + it.rank : " · no correct place")})]);
    const figs = [figure(q.img, ["query", (q.file || "#" + j), "place " + q.place])];
    if (b) figs.push(figure(b.img, ["best: place " + b.place, (b.tour ? b.tour + "/" : "") + (b.file || ""),
                                    run.score_name + " " + score(run, run.score[j])]));
    // The method's own top answer, where it lies in the tolerance band the metrics ignore.
    if (it.top) figs.push(figure(it.top.img, ["top answer: place " + it.top.place,
                                             (it.top.tour ? it.top.tour + "/" : "") + (it.top.file || ""),
                                             "in the ignored band"]));
    if (c) figs.push(figure(c.img, ["correct: place " + c.place, (c.tour ? c.tour + "/" : "") + (c.file || ""),
                                    "rank " + it.rank]));
    return el("div", {cls: "card " + st, "data-query": String(j)},
              [head, el("div", {cls: "imgs"}, figs), ...checkLine(it)]);
  }
  function renderCards(k) {
    const run = D.runs[k], st = states[k], thr = thrOf(k);
    const box = document.getElementById("cards" + k), more = document.getElementById("more" + k);
    box.textContent = "";
    const sel = [];
    for (let j = 0; j < run.n_queries; j++) {
      const s = status(run, j, thr);
      if (st.filter === "all" || st.filter === s || (st.filter === "nopos" && !run.has_pos[j])) sel.push(j);
    }
    sel.slice(0, st.shown).forEach(function (j) { box.appendChild(card(run, j, thr)); });
    more.hidden = sel.length <= st.shown;
    more.textContent = "show more (" + (sel.length - Math.min(st.shown, sel.length)) + " hidden)";
    const counts = {all: run.n_queries, correct: 0, wrong: 0, rejected: 0, nopos: 0};
    for (let j = 0; j < run.n_queries; j++) { counts[status(run, j, thr)]++; if (!run.has_pos[j]) counts.nopos++; }
    document.querySelectorAll("#filters" + k + " button").forEach(function (btn) {
      btn.textContent = btn.dataset.label + " (" + counts[btn.dataset.filter] + ")";
      btn.className = btn.dataset.filter === st.filter ? "on" : "";
    });
  }
  function showScale(k) {
    const run = D.runs[k], box = document.querySelector("#run" + k + " .scale"), rank = states[k].view === "rank";
    box.querySelector(".scale-lo").textContent = rank ? "worst place" : score(run, run.matrix.lo);
    box.querySelector(".scale-hi").textContent = rank ? "best place of the query" : score(run, run.matrix.hi) +
      " (1st-99th percentile)";
  }
  function update(k) {
    const run = D.runs[k], thr = thrOf(k), s = stats(run, thr);
    const set = function (name, v) { document.querySelector("#run" + k + " ." + name).textContent = v; };
    set("v-thr", thr === Infinity ? "above every score" : score(run, thr));
    set("v-acc", s.accepted); set("v-tp", s.tp); set("v-fp", s.fp); set("v-rej", s.rejected);
    set("v-p", fmt(s.precision, 3)); set("v-r", fmt(s.recall, 3));
    drawMatrix(k); renderCards(k); drawPR();
  }

  const container = document.getElementById("runs");
  D.runs.forEach(function (run, k) {
    const st = states[k];
    const slider = el("input", {type: "range", min: "0", max: String(st.thresholds.length), step: "1",
                                value: String(st.index), cls: "thr", "aria-label": "threshold"});
    slider.addEventListener("input", function () { st.index = Number(slider.value); st.shown = PAGE; update(k); });
    const counts = el("div", {cls: "counts"}, [
      el("span", {text: "threshold "}), el("b", {cls: "v-thr"}), el("span", {text: " · accepted "}), el("b", {cls: "v-acc"}),
      el("span", {text: " (correct "}), el("b", {cls: "v-tp"}), el("span", {text: ", wrong "}), el("b", {cls: "v-fp"}),
      el("span", {text: ") · rejected "}), el("b", {cls: "v-rej"}),
      el("span", {text: " · precision "}), el("b", {cls: "v-p"}), el("span", {text: " · recall "}), el("b", {cls: "v-r"})]);
    const dispW = Math.min(720, Math.max(320, run.n_queries * 4));
    const dispH = Math.round(Math.min(720, Math.max(200, dispW * run.n_places / Math.max(run.n_queries, 1))));
    const canvas = el("canvas", {id: "matrix" + k, cls: "matrix", width: String(dispW), height: String(dispH)});
    canvas._imgs = {};
    ["rank", "score"].forEach(function (view) {
      const img = new Image();
      img.onload = function () { if (states[k].view === view) drawMatrix(k); };
      img.src = run.matrix[view];
      canvas._imgs[view] = img;
    });
    // The colour scale of the view shown: rank within the query (worst .. best) or score (1st .. 99th percentile).
    const scale = el("div", {cls: "scale"}, [
      el("span", {cls: "scale-lo"}),
      el("span", {cls: "scale-bar", style: "background: linear-gradient(to right, " + D.colours.join(", ") + ")"}),
      el("span", {cls: "scale-hi"})]);
    const views = el("div", {cls: "views"}, [["rank", "rank within each query"], ["score", "score"]].map(function (v) {
      const id = "view" + k + v[0];
      const input = el("input", {type: "radio", name: "view" + k, id: id, value: v[0]});
      input.checked = v[0] === st.view;
      input.addEventListener("change", function () { st.view = v[0]; showScale(k); drawMatrix(k); });
      return el("label", {"for": id}, [input, el("span", {text: " " + v[1] + " "})]);
    }));
    const filters = el("div", {cls: "filters", id: "filters" + k}, [
      ["all", "all"], ["correct", "correct"], ["wrong", "wrong"], ["rejected", "rejected"], ["nopos", "no correct place"]
    ].map(function (f) {
      const b = el("button", {type: "button", "data-filter": f[0], "data-label": f[1], text: f[1]});
      b.addEventListener("click", function () { st.filter = f[0]; st.shown = PAGE; renderCards(k); });
      return b;
    }));
    const more = el("button", {type: "button", cls: "more", id: "more" + k, text: "show more"});
    more.addEventListener("click", function () { st.shown += PAGE * 2; renderCards(k); });
    const section = el("section", {cls: "run", id: "run" + k}, [
      el("h2", {text: (k + 1) + ". " + run.label}),
      el("p", {cls: "meta", text: run.n_places + " map places × " + run.n_queries + " queries (" + run.n_pos +
                                  " with a correct place); ground truth: " + run.ground_truth + "; folder " + run.dir}),
      el("div", {cls: "controls"}, [el("label", {text: "acceptance threshold "}), slider, counts,
        el("span", {cls: "opened", text: "opened at " + st.opened})]),
      el("div", {cls: "two"}, [
        el("div", {}, [el("h3", {text: "Similarity matrix"}), views, canvas, scale,
          el("p", {cls: "legend", text: "Rows: map places (top = first); columns: queries (left = first). " +
            "Colour: each place's rank among all places for the same query (bright = best; scores of different " +
            "queries are not on one scale, so this view shows the route), or the score itself (scale above). " +
            "White cells: ground truth (correct places" +
            (run.gt_drawn_all ? "" : ", a sample") + "). Dots: the best match of each query accepted at the " +
            "threshold, green when correct, red when wrong."})])]),
      el("h3", {text: "Queries"}),
      el("p", {cls: "legend band", text: "Each card's \u201cbest\u201d is the best place the metrics score: places " +
        "within the ground truth's tolerance band around the query's place (" + run.ground_truth + ") but not " +
        "within its correct places are neither right nor wrong and are skipped. " + (run.n_top_in_band ?
        "For " + run.n_top_in_band + " of " + run.n_queries + " queries the method's top answer lies in that band; " +
        "their cards show it beside the best, as \u201ctop answer\u201d." :
        "For every query here the method's top answer is the best.")}),
      filters, el("div", {cls: "cards", id: "cards" + k}), more]);
    container.appendChild(section);
    showScale(k);
    update(k);
  });
  drawPR();
  document.body.dataset.ready = "1";
})();
