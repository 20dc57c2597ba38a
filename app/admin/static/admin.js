// The admin dashboard's script: live regions, plots, confirmations. Plain JavaScript, no build.
//
// - An element with data-live-url="…" is refreshed by fetching that URL (an HTML fragment) every
//   data-live-interval-ms; jobs and sweeps that change state (elements with data-job-id and
//   data-job-state, or data-sweep-id and data-sweep-state) are announced in #live-announcer, a
//   polite live region, for screen-reader users.
// - <script type="application/json" id="map-figure"> holds a map's plot data (see
//   app/admin/map_figure.py); each .plot element draws one floor of it with plotly.js, every
//   user string escaped (plotlyLiteral).
// - A form with data-confirm="…" asks before it is submitted.
// - On the route tester, clicking the map sets the From or To list; after planning (a page load)
//   the focus goes to the result's heading (or why there is none) and the live region says it.
"use strict";

(function () {
  const announcer = () => document.getElementById("live-announcer");

  function announce(message) {
    const region = announcer();
    if (!region) return;
    region.textContent = "";
    window.setTimeout(() => { region.textContent = message; }, 50);
  }

  // ------------------------------------------------------------------ live regions

  // The state of each job and sweep shown in root, by name ("Job 5", "Sweep 2").
  function jobStates(root) {
    const states = new Map();
    root.querySelectorAll("[data-job-id][data-job-state]").forEach((element) => {
      states.set(`Job ${element.dataset.jobId}`, element.dataset.jobState);
    });
    root.querySelectorAll("[data-sweep-id][data-sweep-state]").forEach((element) => {
      states.set(`Sweep ${element.dataset.sweepId}`, element.dataset.sweepState);
    });
    return states;
  }

  function startLive(container) {
    const url = container.dataset.liveUrl;
    const interval = Number(container.dataset.liveIntervalMs || 2000);
    let stopped = false;

    async function refresh() {
      if (stopped) return;
      if (document.hidden) { window.setTimeout(refresh, interval); return; }
      try {
        const response = await fetch(url, { credentials: "same-origin", headers: { Accept: "text/html" } });
        if (response.redirected && new URL(response.url).pathname === "/admin/login") {
          stopped = true;
          announce("Your login ended: reload the page to log in again.");
          return;
        }
        if (response.ok) {
          const html = await response.text();
          if (html !== container.dataset.liveHtml) swap(container, html);
        }
      } catch (error) {
        // The server is restarting or the network is down: try again at the next tick.
      }
      window.setTimeout(refresh, interval);
    }
    window.setTimeout(refresh, interval);
  }

  // What identifies the focused element across a swap: its id, else its link or form target.
  function focusKey(element) {
    if (element.id) return "#" + CSS.escape(element.id);
    const href = element.getAttribute("href");
    if (href) return `a[href="${CSS.escape(href)}"]`;
    const form = element.form;
    if (form && form.getAttribute("action")) {
      return `form[action="${CSS.escape(form.getAttribute("action"))}"] button`;
    }
    return null;
  }

  function swap(container, html) {
    const before = jobStates(container);
    const focused = document.activeElement;
    const key = focused && container.contains(focused) ? focusKey(focused) : null;
    container.innerHTML = html;
    container.dataset.liveHtml = html;
    const after = jobStates(container);
    const changes = [];
    after.forEach((state, name) => {
      if (before.has(name) && before.get(name) !== state) changes.push(`${name}: ${state}.`);
      if (!before.has(name)) changes.push(`New ${name.toLowerCase()}: ${state}.`);
    });
    if (changes.length) announce(changes.join(" "));
    if (key) {
      const again = container.querySelector(key);
      if (again) again.focus();
    }
  }

  // ------------------------------------------------------------------ plots

  const COLOURS = {
    raw: "#767676",
    optimized: "#0b4fa8",
    walk: "#6a1b9a",
    stairs: "#b3261e",
    tags: "#1e6b2a",
    pois: "#1b1b1b",
    route: "#d35400",
  };
  // one colour per session of a map of several (distinct for common colour blindness)
  const SESSION_COLOURS = ["#0b4fa8", "#e69f00", "#009e73", "#cc79a7", "#56b4e9", "#8c564b"];

  // plotly.js reads the text it draws as markup (<a href>, <span style>, <br>, <b>, …; it
  // decodes &lt; &gt; &amp;): every string from a user (a point of interest's name, …) goes
  // through this, so that it is drawn as written and never becomes a link or styled text.
  function plotlyLiteral(text) {
    return String(text).replace(/&/g, "&amp;").replace(/</g, "&lt;").replace(/>/g, "&gt;");
  }

  function lineTrace(line, name, colour, extra) {
    return Object.assign({
      type: "scatter", mode: "lines", name: name, x: line.x, y: line.z,
      line: { color: colour, width: 1.5 }, hoverinfo: "skip", connectgaps: false,
    }, extra || {});
  }

  function floorTraces(floor) {
    const traces = [];
    if (floor.raw) traces.push(lineTrace(floor.raw, "Raw odometry", COLOURS.raw, { line: { color: COLOURS.raw, width: 1 } }));
    if (floor.sessions) {
      floor.sessions.forEach((session, k) => {
        const colour = SESSION_COLOURS[k % SESSION_COLOURS.length];
        traces.push(lineTrace(session.line, session.name + " (optimized)", colour, { hoverinfo: "x+y" }));
      });
    } else {
      traces.push(lineTrace(floor.optimized, "Optimized trajectory", COLOURS.optimized, { hoverinfo: "x+y" }));
    }
    if (floor.walk) traces.push(lineTrace(floor.walk, "Path graph", COLOURS.walk, { line: { color: COLOURS.walk, width: 1.5, dash: "dot" } }));
    if (floor.stairs) traces.push(lineTrace(floor.stairs, "Stairs and elevators", COLOURS.stairs, { line: { color: COLOURS.stairs, width: 3 } }));
    traces.push(lineTrace(floor.ellipses, "Tag uncertainty (2σ)", COLOURS.tags, { line: { color: COLOURS.tags, width: 1 } }));
    traces.push({
      type: "scatter", mode: "markers+text", name: "Tags",
      x: floor.tags.map((t) => t.x), y: floor.tags.map((t) => t.z),
      text: floor.tags.map((t) => plotlyLiteral(t.id)), textposition: "top right",
      customdata: floor.tags.map((t) => "tag:" + t.id),
      hovertext: floor.tags.map((t) => `Tag ${t.id}: ${t.detections} detections`),
      hoverinfo: "text",
      marker: { symbol: "square", size: 9, color: COLOURS.tags },
    });
    if (floor.pois.length) {
      traces.push({
        type: "scatter", mode: "markers+text", name: "Points of interest",
        x: floor.pois.map((p) => p.x), y: floor.pois.map((p) => p.z),
        text: floor.pois.map((p) => plotlyLiteral(p.name)), textposition: "bottom right",
        customdata: floor.pois.map((p) => "poi:" + p.name),
        hoverinfo: "text",
        marker: { symbol: "star", size: 13, color: COLOURS.pois },
      });
    }
    if (floor.route) traces.push(lineTrace(floor.route, "Route", COLOURS.route, { line: { color: COLOURS.route, width: 5 } }));
    return traces;
  }

  function drawPlots() {
    const source = document.getElementById("map-figure");
    if (!source || typeof window.Plotly === "undefined") return;
    const figure = JSON.parse(source.textContent);
    figure.floors.forEach((floor) => {
      const element = document.getElementById("plot-floor-" + floor.index);
      if (!element) return;
      const layout = {
        margin: { l: 60, r: 20, t: 20, b: 50 },
        xaxis: { title: { text: "x (m)" }, zeroline: false },
        yaxis: { title: { text: "z (m)" }, autorange: "reversed", scaleanchor: "x", scaleratio: 1, zeroline: false },
        legend: { orientation: "h", y: -0.15 },
        hovermode: "closest",
        font: { color: "#1b1b1b" },
      };
      window.Plotly.newPlot(element, floorTraces(floor), layout, {
        responsive: true, displaylogo: false, displayModeBar: false, scrollZoom: true,
      }).then(() => {
        element.dataset.rendered = "true";
        element.dispatchEvent(new CustomEvent("plot-rendered", { bubbles: true }));
      });
      if (document.getElementById("route-form")) {
        element.on("plotly_click", (event) => chooseFromPlot(event, floor));
      }
    });
  }

  // ------------------------------------------------------------------ route tester

  function chooseFromPlot(event, floor) {
    if (!event.points || !event.points.length) return;
    const point = event.points[0];
    const which = (document.querySelector('input[name="click_sets"]:checked') || {}).value || "from";
    const select = document.getElementById("route-" + which);
    if (!select) return;
    let value = point.customdata;
    let label;
    if (typeof value !== "string") {
      const x = Number(point.x).toFixed(2);
      const z = Number(point.y).toFixed(2);
      value = `pos:${x},${floor.level_m || 0},${z}`;
      label = `The place clicked on the map (x ${x} m, z ${z} m, ${floor.name})`;
      let option = select.querySelector("option[data-clicked]");
      if (!option) {
        option = document.createElement("option");
        option.dataset.clicked = "true";
        select.insertBefore(option, select.options[1] || null);
      }
      option.value = value;
      option.textContent = label;
    } else {
      const option = Array.from(select.options).find((o) => o.value === value);
      label = option ? option.textContent : value;
    }
    select.value = value;
    announce(`${which === "from" ? "From" : "To"}: ${label}.`);
  }

  // ------------------------------------------------------------------ start

  document.addEventListener("submit", (event) => {
    const form = event.target;
    if (form instanceof HTMLFormElement && form.dataset.confirm && !window.confirm(form.dataset.confirm)) {
      event.preventDefault();
    }
  });

  // The route tester reloads the page to plan: the result (or why there is none) gets the
  // focus and is said, instead of the focus starting again at the top in silence.
  function announceRoute() {
    const heading = document.querySelector("#route-result h2");
    const error = document.getElementById("route-error");
    if (heading) {
      heading.tabIndex = -1;
      heading.focus();
      const steps = Array.from(document.querySelectorAll("#route-steps li")).map((li) => li.textContent.trim());
      announce(`${heading.textContent.trim()}, ${steps.length} steps: ${steps.join("; ")}.`);
    } else if (error) {
      error.tabIndex = -1;
      error.focus();
      announce(`No route: ${error.textContent.trim()}`);
    }
  }

  document.addEventListener("DOMContentLoaded", () => {
    document.querySelectorAll("[data-live-url]").forEach(startLive);
    drawPlots();
    announceRoute();
  });
})();
