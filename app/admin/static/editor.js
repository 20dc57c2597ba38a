// The corridor editor (issue 27): the floor's corridor graph drawn by hand in SVG, edited with
// the mouse and the keyboard. Plain JavaScript, no build. See app/admin/pages/editor.py for the
// JSON endpoints it talks to; every edit goes through the server, which checks it, and the page
// then draws the graph the server serves (so what is seen is what routes use).
//
// State: the data of the current version (nodes, edges, tags, points of interest, walks, edits),
// the floor shown, the view (centre and scale), the selection (a node or an edge), a move being
// made (pending until dropped or Enter), a connection being made (from a node), the place
// clicked last, and an undo stack of what this page did (an edit added: delete it; an edit
// deleted: add it again).
//
// Keyboard and screen reader: nodes and edges are focusable buttons in the SVG (each edge comes
// right after the node with its smaller id, in tab order); [ and ] walk along the corridor from
// the selected edge (on through its far node, the straightest way), { and } turn around a node;
// the same graph is a pair of tables (#editor-nodes, #editor-edges) with the same actions as
// buttons; every outcome is said in the page's live region (#live-announcer), once.
"use strict";

(function () {
  const SVG = "http://www.w3.org/2000/svg";
  const root = document.getElementById("editor");
  if (!root) return;
  const mapId = root.dataset.mapId;
  const base = `/admin/maps/${mapId}/editor`;
  const csrf = (document.querySelector('meta[name="csrf-token"]') || {}).content || "";
  const canvas = document.getElementById("editor-canvas");
  const statusLine = document.getElementById("editor-status");
  const errorLine = document.getElementById("editor-error");
  const floorSelect = document.getElementById("editor-floor");
  const kindSelect = document.getElementById("editor-kind");
  const history = document.getElementById("editor-history");
  const W = 800;
  const H = 560;
  const MOVE_STEP_M = 0.5;
  const FINE_STEP_M = 0.1;

  const state = {
    data: null,
    floor: 0,
    view: { cx: 0, cz: 0, scale: 10 },
    selected: null, // {type: "node", id} | {type: "edge", from, to, toward}: toward is the end
    // that ] walks on through (the direction of travel along the corridor)
    pending: null, // {id, x, z}: a move not sent yet
    connectFrom: null, // a node id
    place: null, // {x, z}: the background point clicked last
    undo: [],
    drag: null,
    busy: false,
    quietFocus: false, // focus moved by the page itself (a redraw): not a choice to announce
  };

  // ------------------------------------------------------------------ helpers

  // The status line shows the message; the page's live region (one, polite) says it, emptied
  // first so that the same message twice is said twice.
  function announce(message) {
    statusLine.textContent = message;
    const region = document.getElementById("live-announcer");
    if (region) {
      region.textContent = "";
      window.setTimeout(() => { region.textContent = message; }, 50);
    }
  }

  // One change at a time: while one is saved (and the graph drawn again), the editor says so
  // (aria-busy) and a key or click that would start another is told to wait, never dropped
  // silently.
  function startBusy() {
    if (state.busy) {
      announce("Still saving the last change; try again in a moment.");
      return false;
    }
    state.busy = true;
    root.setAttribute("aria-busy", "true");
    return true;
  }

  function endBusy() {
    state.busy = false;
    root.removeAttribute("aria-busy");
  }

  function showError(message) {
    errorLine.textContent = message;
    errorLine.hidden = !message;
  }

  function el(name, attributes, parent) {
    const element = document.createElementNS(SVG, name);
    Object.entries(attributes || {}).forEach(([key, value]) => element.setAttribute(key, value));
    if (parent) parent.appendChild(element);
    return element;
  }

  function fixed(value) { return Math.round(value * 1000) / 1000; }
  function shown(x, z) { return `x ${x.toFixed(1)} m, z ${z.toFixed(1)} m`; }

  function toScreen(x, z) {
    const v = state.view;
    return [(x - v.cx) * v.scale + W / 2, (z - v.cz) * v.scale + H / 2];
  }

  function toMap(sx, sy) {
    const v = state.view;
    return [(sx - W / 2) / v.scale + v.cx, (sy - H / 2) / v.scale + v.cz];
  }

  function pointerToSvg(event) {
    const box = canvas.getBoundingClientRect();
    return [(event.clientX - box.left) * (W / box.width), (event.clientY - box.top) * (H / box.height)];
  }

  function node(id) { return state.data.nodeById.get(id); }

  function position(id) {
    const n = node(id);
    if (state.pending && state.pending.id === id) return [state.pending.x, state.pending.z];
    return [n.x, n.z];
  }

  function level() {
    const floor = state.data.floors.find((f) => f.index === state.floor);
    return floor ? floor.level_m : 0;
  }

  function point(n) { return [fixed(n.x), fixed(n.y), fixed(n.z)]; }

  // ------------------------------------------------------------------ talking to the server

  async function request(method, url, body) {
    const headers = { Accept: "application/json" };
    if (method !== "GET") headers["X-CSRF-Token"] = csrf;
    if (body !== undefined) headers["Content-Type"] = "application/json";
    const response = await fetch(url, {
      method, headers, credentials: "same-origin",
      body: body === undefined ? undefined : JSON.stringify(body),
    });
    let answer = null;
    try { answer = await response.json(); } catch (error) { answer = null; }
    if (!response.ok) {
      const detail = answer && answer.detail ? answer.detail : `the server answered ${response.status}`;
      const error = new Error(detail);
      error.status = response.status;
      throw error;
    }
    return answer;
  }

  async function load() {
    const data = await request("GET", `${base}/data`);
    data.nodeById = new Map(data.nodes.map((n) => [n.id, n]));
    data.around = new Map(data.nodes.map((n) => [n.id, []]));
    data.edges.forEach((e) => {
      [e.from, e.to].forEach((id) => { if (data.around.has(id)) data.around.get(id).push(e); });
    });
    const first = state.data === null;
    state.data = data;
    if (state.selected && state.selected.type === "node" && !data.nodeById.has(state.selected.id)) {
      state.selected = null;
    }
    if (first) fit();
    fillPoiLists();
    draw();
    drawHistory();
  }

  // Send an edit; remember how to undo it (unless it is an undo itself). then(answer): what to
  // do once the graph is drawn again (select the new edge, …).
  async function sendEdit(edit, description, { remember = true, replaces = null, then = null } = {}) {
    if (!startBusy()) return;
    showError("");
    try {
      const answer = await request("POST", `${base}/edits`, edit);
      if (remember) state.undo.push({ kind: "added", id: answer.id, description });
      if (replaces !== null) renumber(replaces, answer.id);
      state.pending = null;
      state.connectFrom = null;
      await load();
      const more = then ? then(answer) : "";
      announce(`${description}: done (edit ${answer.id}).${more ? " " + more : ""}`);
      await planRoute(false);
    } catch (error) {
      showError(`${description}: ${error.message}`);
      announce(`${description} refused: ${error.message}`);
    } finally {
      endBusy();
    }
  }

  async function deleteEdit(id, edit, { remember = true, said = null } = {}) {
    if (!startBusy()) return;
    showError("");
    try {
      await request("DELETE", `${base}/edits/${id}`);
      if (remember) state.undo.push({ kind: "deleted", id, edit, description: describe(edit) });
      await load();
      announce(said || `Edit ${id} deleted.`);
      await planRoute(false);
    } catch (error) {
      showError(`Deleting edit ${id}: ${error.message}`);
      announce(`Deleting edit ${id} failed: ${error.message}`);
    } finally {
      endBusy();
    }
  }

  // An edit deleted and added again has a new id: what the undo stack says of the old one is
  // said of the new one.
  function renumber(oldId, newId) {
    state.undo.forEach((entry) => { if (entry.id === oldId) entry.id = newId; });
  }

  async function undo() {
    if (state.busy) { startBusy(); return; } // says "still saving"; the undo is kept
    const last = state.undo.pop();
    if (!last) { announce("Nothing to undo."); return; }
    if (last.kind === "added") {
      await deleteEdit(last.id, null, { remember: false, said: `Undone: ${last.description} (edit ${last.id} deleted).` });
    } else {
      await sendEdit(last.edit, `Undo the deletion of ${last.description}`, { remember: false, replaces: last.id });
    }
  }

  // ------------------------------------------------------------------ drawing

  function fit() {
    const nodes = state.data.nodes.filter((n) => n.floor === state.floor);
    const things = nodes.concat(state.data.tags.filter((t) => t.floor === state.floor));
    if (!things.length) return;
    const xs = things.map((n) => n.x);
    const zs = things.map((n) => n.z);
    const minX = Math.min(...xs), maxX = Math.max(...xs), minZ = Math.min(...zs), maxZ = Math.max(...zs);
    state.view.cx = (minX + maxX) / 2;
    state.view.cz = (minZ + maxZ) / 2;
    state.view.scale = Math.min(W / Math.max(maxX - minX + 4, 4), H / Math.max(maxZ - minZ + 4, 4));
  }

  function edgeKey(edge) { return `${edge.from}-${edge.to}`; }
  function other(edge, id) { return edge.from === id ? edge.to : edge.from; }
  function edgesAt(id) { return state.data.around.get(id) || []; }
  function findEdge(from, to) {
    return state.data.edges.find((e) => (e.from === from && e.to === to) || (e.from === to && e.to === from));
  }
  function isSelectedEdge(edge) {
    const s = state.selected;
    return !!s && s.type === "edge" && s.from === edge.from && s.to === edge.to;
  }
  function edgeName(edge, toward) {
    const end = toward === undefined ? edge.to : toward;
    return `Edge from node ${other(edge, end)} to node ${end}, ${edge.kind}, ${edge.length_m.toFixed(1)} m`;
  }
  function nodeName(n) {
    return `Node ${n.id}, ${n.kind}${n.quiet ? ", quiet" : ""}, ${shown(n.x, n.z)}, ${edgesAt(n.id).length} edges`;
  }

  // What has the keyboard focus in the graph or its tables, to give it back after a redraw.
  function focusedKey() {
    const active = document.activeElement;
    if (!active || active === document.body) return null;
    if (canvas.contains(active) && active.dataset) {
      if (active.dataset.node !== undefined) return { node: active.dataset.node };
      if (active.dataset.edge !== undefined) return { edge: active.dataset.edge };
    }
    if (active.id && document.getElementById("editor-tables").contains(active)) return { id: active.id };
    return null;
  }

  // Focus an element without it counting as the user's choice (no announcement, no new
  // selection).
  function focusQuietly(element) {
    if (!element) return false;
    state.quietFocus = true;
    try { element.focus({ preventScroll: true }); } finally { state.quietFocus = false; }
    return true;
  }

  function restoreFocus(key) {
    if (!key) return;
    if (key.node !== undefined || key.edge !== undefined) {
      const again = key.node !== undefined
        ? canvas.querySelector(`[data-node="${key.node}"]`)
        : canvas.querySelector(`[data-edge="${key.edge}"]`);
      // gone (an edge removed, another floor): the selection, else the graph itself
      if (!focusQuietly(again) && !focusSelected()) focusQuietly(canvas);
    } else if (key.id && !focusQuietly(document.getElementById(key.id))) {
      // its row is gone (an edge removed): the table it was in
      focusQuietly(document.getElementById(key.id.startsWith("edge-") ? "editor-edges" : "editor-nodes"));
    }
  }

  function focusSelected() {
    const s = state.selected;
    if (!s) return false;
    const element = s.type === "node"
      ? canvas.querySelector(`[data-node="${s.id}"]`)
      : canvas.querySelector(`[data-edge="${s.from}-${s.to}"]`);
    return focusQuietly(element);
  }

  // draw(): the SVG and the tables (their rows made again only when the graph changes), and the
  // focus given back to what had it.
  function draw() {
    const data = state.data;
    const focused = focusedKey();
    canvas.replaceChildren();
    const floorNodes = data.nodes.filter((n) => n.floor === state.floor).sort((a, b) => a.id - b.id);
    const here = new Set(floorNodes.map((n) => n.id));
    // the walks, faint
    const walk = (data.floors.find((f) => f.index === state.floor) || {}).walk;
    if (walk && walk.x.length) {
      let d = "";
      let pen = "M";
      walk.x.forEach((x, k) => {
        const z = walk.z[k];
        if (x === null || z === null) { pen = "M"; return; }
        const [sx, sy] = toScreen(x, z);
        d += `${pen}${sx.toFixed(1)} ${sy.toFixed(1)} `;
        pen = "L";
      });
      el("path", { d, class: "walk", "aria-hidden": "true" }, canvas);
    }
    // the route planned last
    if (state.route) {
      const points = state.route.polyline.filter((p) => Math.abs(p[1] - level()) < 1.5);
      if (points.length > 1) {
        const d = points.map((p, k) => {
          const [sx, sy] = toScreen(p[0], p[2]);
          return `${k ? "L" : "M"}${sx.toFixed(1)} ${sy.toFixed(1)}`;
        }).join(" ");
        el("path", { d, class: "route", "aria-hidden": "true" }, canvas);
      }
    }
    // edges: a visible line and a wide one to click (the focusable one comes with its node)
    const edgeLayer = el("g", { class: "edges", "aria-hidden": "true" }, canvas);
    const ends = new Map(); // edge key -> its line's ends on screen
    const owned = new Map(); // node id -> the edges that follow it in tab order
    data.edges.forEach((edge) => {
      const a = here.has(edge.from), b = here.has(edge.to);
      if (!a && !b) return;
      const [x1, y1] = toScreen(...position(a ? edge.from : edge.to));
      let [x2, y2] = toScreen(...position(b ? edge.to : edge.from));
      if (!(a && b)) { x2 += 14; y2 -= 14; } // a floor change: a stub toward the other floor
      const selected = isSelectedEdge(edge);
      el("line", { x1, y1, x2, y2, class: `edge edge-${edge.kind}${selected ? " selected" : ""}` }, edgeLayer);
      const hit = el("line", { x1, y1, x2, y2, class: "edge-hit", "data-from": edge.from, "data-to": edge.to }, edgeLayer);
      hit.addEventListener("pointerdown", (event) => {
        event.stopPropagation();
        event.preventDefault(); // the focus goes to the edge, not to the SVG
        selectEdge(edge.from, edge.to);
      });
      ends.set(edgeKey(edge), [x1, y1, x2, y2]);
      const owner = a && b ? Math.min(edge.from, edge.to) : (a ? edge.from : edge.to);
      if (!owned.has(owner)) owned.set(owner, []);
      owned.get(owner).push(edge);
    });
    // tags and points of interest, their labels placed apart (below)
    const marks = [];
    const labels = [];
    data.tags.filter((t) => t.floor === state.floor).forEach((tag) => {
      const [sx, sy] = toScreen(tag.x, tag.z);
      el("rect", { x: sx - 4, y: sy - 4, width: 8, height: 8, class: "tag", "aria-hidden": "true" }, canvas);
      marks.push([sx - 4, sy - 4, sx + 4, sy + 4]);
      labels.push({ text: String(tag.id), x: sx, y: sy, r: 5, size: 11, className: "tag-label", priority: 1 });
    });
    data.pois.filter((p) => p.floor === state.floor).forEach((poi) => {
      const [sx, sy] = toScreen(poi.x, poi.z);
      el("path", { d: `M${sx} ${sy - 7}L${sx + 7} ${sy}L${sx} ${sy + 7}L${sx - 7} ${sy}Z`, class: "poi", "aria-hidden": "true" }, canvas);
      marks.push([sx - 7, sy - 7, sx + 7, sy + 7]);
      labels.push({ text: poi.name, x: sx, y: sy, r: 8, size: 12, className: "poi-label", priority: 2 });
    });
    // the nodes are obstacles too (drawn above the labels, they would hide them)
    const nodeBoxes = floorNodes.map((n) => {
      const [sx, sy] = toScreen(...position(n.id));
      return [sx - 7, sy - 7, sx + 7, sy + 7];
    });
    drawLabels(labels, marks, nodeBoxes);
    // the place clicked
    if (state.place) {
      const [sx, sy] = toScreen(state.place.x, state.place.z);
      el("path", { d: `M${sx - 6} ${sy}H${sx + 6}M${sx} ${sy - 6}V${sy + 6}`, class: "place", "aria-hidden": "true" }, canvas);
    }
    // nodes: focusable buttons, each followed by its edges (focusable too; drawn by the edge layer)
    const nodeLayer = el("g", { class: "nodes" }, canvas);
    floorNodes.forEach((n) => {
      const [sx, sy] = toScreen(...position(n.id));
      const selected = state.selected && state.selected.type === "node" && state.selected.id === n.id;
      const classes = ["node", `node-${n.kind}`];
      if (n.quiet) classes.push("quiet");
      if (selected) classes.push("selected");
      if (state.connectFrom === n.id) classes.push("connecting");
      const circle = el("circle", {
        cx: sx.toFixed(1), cy: sy.toFixed(1), r: n.kind === "junction" ? 7 : 6,
        class: classes.join(" "), tabindex: "0", role: "button",
        "aria-pressed": selected ? "true" : "false",
        "aria-label": nodeName(n),
        "data-node": String(n.id),
      }, nodeLayer);
      circle.addEventListener("pointerdown", (event) => nodePointerDown(event, n.id));
      circle.addEventListener("focus", () => {
        if (state.quietFocus) return;
        if (!(state.selected && state.selected.type === "node" && state.selected.id === n.id)) selectNode(n.id, false);
      });
      (owned.get(n.id) || []).forEach((edge) => {
        const [x1, y1, x2, y2] = ends.get(edgeKey(edge));
        const selectedEdge = isSelectedEdge(edge);
        const line = el("line", {
          x1, y1, x2, y2, class: "edge-focus", tabindex: "0", role: "button",
          "aria-pressed": selectedEdge ? "true" : "false",
          "aria-label": edgeName(edge, selectedEdge ? state.selected.toward : undefined),
          "data-edge": edgeKey(edge),
        }, nodeLayer);
        line.addEventListener("focus", () => {
          if (state.quietFocus || isSelectedEdge(edge)) return;
          selectEdge(edge.from, edge.to, { focus: false });
        });
      });
    });
    drawTables();
    restoreFocus(focused);
  }

  // Labels of tags and points of interest, placed so that none covers another, a mark or a node: each
  // tries spots around its mark (right, left, above, below), then farther out with a leader
  // line to its mark; one that finds no free spot is left out, tags before points of interest
  // (the tables and the lists name them all).
  function drawLabels(labels, marks, obstacles) {
    const taken = marks.map((box) => box.slice());
    const blocked = obstacles.map((box) => box.slice());
    const layer = el("g", { class: "labels", "aria-hidden": "true" }, canvas);
    const mine = (box, label) => box[0] >= label.x - label.r - 0.5 && box[2] <= label.x + label.r + 0.5
      && box[1] >= label.y - label.r - 0.5 && box[3] <= label.y + label.r + 0.5;
    const order = labels.slice().sort((a, b) => b.priority - a.priority);
    order.forEach((label) => {
      const w = label.text.length * label.size * 0.62 + 2;
      const h = label.size + 2;
      const spots = [];
      [0, 1, 2, 3].forEach((ring) => {
        const d = label.r + 2 + ring * 14;
        spots.push([d, -h / 2], [-d - w, -h / 2], [-w / 2, -d - h], [-w / 2, d],
          [d, -d - h + 4], [d, d - 4], [-d - w, -d - h + 4], [-d - w, d - 4]);
      });
      const own = taken.find((t) => mine(t, label)); // its own mark does not block it
      const others = (own ? taken.filter((t) => t !== own) : taken).concat(blocked);
      const spot = spots.find(([dx, dy]) => {
        const box = [label.x + dx, label.y + dy, label.x + dx + w, label.y + dy + h];
        if (box[0] < 0 || box[1] < 0 || box[2] > W || box[3] > H) return false;
        return !others.some((t) => box[0] < t[2] && box[2] > t[0] && box[1] < t[3] && box[3] > t[1]);
      });
      if (!spot) return;
      const box = [label.x + spot[0], label.y + spot[1], label.x + spot[0] + w, label.y + spot[1] + h];
      taken.push(box);
      const far = Math.hypot(box[0] + w / 2 - label.x, box[1] + h / 2 - label.y) > label.r + w / 2 + 12;
      if (far) {
        const tx = Math.min(Math.max(label.x, box[0]), box[2]);
        const ty = Math.min(Math.max(label.y, box[1]), box[3]);
        el("line", { x1: label.x, y1: label.y, x2: tx, y2: ty, class: "leader" }, layer);
      }
      const text = el("text", { x: box[0] + 1, y: box[3] - 3, class: label.className }, layer);
      text.textContent = label.text;
    });
  }

  // The graph of the floor shown as two tables (what a screen reader walks), with the keys'
  // actions as buttons.
  function button(id, text, label, action, pressed) {
    const b = document.createElement("button");
    b.type = "button";
    b.id = id;
    b.className = "button secondary small";
    b.textContent = text;
    b.setAttribute("aria-label", label);
    if (pressed !== undefined) b.setAttribute("aria-pressed", pressed ? "true" : "false");
    b.addEventListener("click", (event) => { event.stopPropagation(); action(); });
    return b;
  }

  function cell(row, text, header) {
    const c = document.createElement(header ? "th" : "td");
    if (header) c.scope = "row";
    c.textContent = text;
    row.appendChild(c);
    return c;
  }

  // The rows are made again when the graph, the floor or the connection being made changes; a
  // new selection only marks its rows (a walk with Tab through hundreds of nodes stays quick).
  function drawTables() {
    const data = state.data;
    const key = [data.revision, data.map_version, state.floor, state.connectFrom, data.nodes.length, data.edges.length].join("|");
    if (state.tablesKey !== key || state.tablesData !== data) {
      state.tablesKey = key;
      state.tablesData = data;
      fillTables();
    }
    markSelectedRows();
  }

  function fillTables() {
    const data = state.data;
    const floorName = floorSelect.options[floorSelect.selectedIndex] ? floorSelect.options[floorSelect.selectedIndex].text : "the floor";
    const nodes = data.nodes.filter((n) => n.floor === state.floor).sort((a, b) => a.id - b.id);
    const here = new Set(nodes.map((n) => n.id));
    const edges = data.edges.filter((e) => here.has(e.from) || here.has(e.to));
    document.getElementById("editor-nodes-caption").textContent = `Nodes on ${floorName} (${nodes.length})`;
    document.getElementById("editor-edges-caption").textContent = `Edges on ${floorName} (${edges.length})`;
    const nodeRows = nodes.map((n) => {
      const row = document.createElement("tr");
      row.dataset.row = `node:${n.id}`;
      cell(row, `Node ${n.id}${state.connectFrom === n.id ? " (connecting from)" : ""}`, true).dataset.name = "true";
      cell(row, `${n.kind}${n.quiet ? ", quiet" : ""}`);
      cell(row, shown(n.x, n.z));
      cell(row, edgesAt(n.id).map((e) => other(e, n.id)).join(", ") || "none");
      const actions = cell(row, "");
      actions.append(button(`node-${n.id}-select`, "Select", `Select node ${n.id}`, () => selectNode(n.id, false), false));
      actions.append(" ", button(`node-${n.id}-quiet`, "Quiet", `Quiet node ${n.id}`, () => { selectNode(n.id, false, false); quiet(); }));
      let connect;
      if (state.connectFrom === null) {
        connect = button(`node-${n.id}-connect`, "Connect from", `Connect from node ${n.id}`, () => { selectNode(n.id, false, false); startConnect(false); });
      } else if (state.connectFrom === n.id) {
        connect = button(`node-${n.id}-connect`, "Cancel connecting", `Cancel connecting from node ${n.id}`, () => cancel());
      } else {
        connect = button(`node-${n.id}-connect`, "Connect to", `Connect node ${state.connectFrom} to node ${n.id}`, () => { selectNode(n.id, false, false); connectTo(n.id); });
      }
      actions.append(" ", connect);
      return row;
    });
    document.querySelector("#editor-nodes tbody").replaceChildren(...nodeRows);
    const edgeRows = edges.map((e) => {
      const row = document.createElement("tr");
      row.dataset.row = `edge:${edgeKey(e)}`;
      cell(row, `Node ${e.from} to node ${e.to}`, true).dataset.name = "true";
      cell(row, e.kind);
      cell(row, `${e.length_m.toFixed(1)} m`);
      const actions = cell(row, "");
      actions.append(button(`edge-${edgeKey(e)}-select`, "Select", `Select the edge from node ${e.from} to node ${e.to}`, () => selectEdge(e.from, e.to, { focus: false }), false));
      actions.append(" ", button(`edge-${edgeKey(e)}-remove`, "Remove", `Remove the edge from node ${e.from} to node ${e.to}`, () => { selectEdge(e.from, e.to, { focus: false, say: false }); removeEdge(); }));
      return row;
    });
    document.querySelector("#editor-edges tbody").replaceChildren(...edgeRows);
    state.markedRow = null;
  }

  // The selected node's or edge's row: "(selected)", aria-current, its Select button pressed.
  function markSelectedRows() {
    const s = state.selected;
    const want = !s ? null : s.type === "node" ? `node:${s.id}` : `edge:${s.from}-${s.to}`;
    if (state.markedRow === want) return;
    const mark = (rowKey, on) => {
      if (!rowKey) return;
      const row = document.getElementById("editor-tables").querySelector(`tr[data-row="${rowKey}"]`);
      if (!row) return;
      if (on) row.setAttribute("aria-current", "true"); else row.removeAttribute("aria-current");
      const name = row.querySelector("[data-name]");
      name.textContent = name.textContent.replace(/ \(selected\)$/, "") + (on ? " (selected)" : "");
      const select = row.querySelector('button[id$="-select"]');
      if (select) select.setAttribute("aria-pressed", on ? "true" : "false");
    };
    mark(state.markedRow, false);
    mark(want, true);
    state.markedRow = want;
  }

  function drawHistory() {
    history.replaceChildren();
    if (!state.data.edits.length) {
      const item = document.createElement("li");
      item.textContent = "No edit yet.";
      history.appendChild(item);
      return;
    }
    state.data.edits.forEach((entry) => {
      const item = document.createElement("li");
      item.className = entry.applied ? "edit-applied" : "edit-not-applied";
      item.dataset.editId = String(entry.id);
      const what = document.createElement("span");
      what.textContent = `Edit ${entry.id}: ${describe(entry.edit)}. `;
      const how = document.createElement("strong");
      how.textContent = entry.applied ? "Applied" : `Not applied: ${entry.reason}`;
      const who = document.createElement("span");
      who.className = "who-when";
      who.textContent = ` — ${entry.who}, ${entry.created_at} `;
      const remove = document.createElement("button");
      remove.type = "button";
      remove.className = "button secondary small";
      remove.textContent = "Delete";
      remove.setAttribute("aria-label", `Delete edit ${entry.id}`);
      remove.addEventListener("click", () => deleteEdit(entry.id, entry.edit));
      item.append(what, how, who, remove);
      history.appendChild(item);
    });
  }

  function describe(edit) {
    if (!edit) return "an edit";
    const at = (p) => (p ? `(${p[0].toFixed(1)}, ${p[2].toFixed(1)})` : "");
    switch (edit.op) {
      case "quiet": return `quiet at ${at(edit.at)}`;
      case "add_edge": return `add a ${edit.kind} from ${at(edit.from)} to ${at(edit.to)}`;
      case "remove_edge": return `remove the edge from ${at(edit.from)} to ${at(edit.to)}`;
      case "move_node": return `move the node at ${at(edit.from)} to ${at(edit.to)}`;
      case "add_poi": return `add point of interest “${edit.name}” at ${at(edit.at)}`;
      case "rename_poi": return `rename “${edit.name}” to “${edit.new_name}”`;
      case "remove_poi": return `remove point of interest “${edit.name}”`;
      default: return String(edit.op);
    }
  }

  function fillPoiLists() {
    const data = state.data;
    const existing = document.getElementById("poi-existing");
    const chosen = existing.value;
    existing.replaceChildren(...data.pois.map((p) => new Option(p.name, p.name)));
    if (chosen) existing.value = chosen;
    ["editor-from", "editor-to"].forEach((id, k) => {
      const select = document.getElementById(id);
      const before = select.value;
      const options = data.tags.map((t) => new Option(`Tag ${t.id}`, `tag:${t.id}`))
        .concat(data.pois.map((p) => new Option(p.name, `poi:${p.name}`)));
      select.replaceChildren(...options);
      if (before && options.some((o) => o.value === before)) select.value = before;
      else if (options.length) select.value = options[k === 0 ? 0 : options.length - 1].value;
    });
  }

  // ------------------------------------------------------------------ selecting

  // Select a node: draw it selected, focus it (focus: the SVG's node; false: where the focus
  // is, e.g. the table's button), say so (say: false, when an action that says more follows).
  function selectNode(id, focus = true, say = true) {
    state.selected = { type: "node", id };
    const n = node(id);
    draw();
    if (focus) focusSelected();
    if (!say) return;
    const joining = state.connectFrom !== null && state.connectFrom !== id
      ? ` Press Enter to connect node ${state.connectFrom} to it.` : "";
    announce(`${nodeName(n).replace(/^Node (\d+)/, "Node $1 selected")}.${joining}`);
  }

  function selectEdge(from, to, { focus = true, toward = undefined, say = true, more = "" } = {}) {
    const edge = findEdge(from, to);
    if (!edge) return;
    const end = toward === undefined ? edge.to : toward;
    state.selected = { type: "edge", from: edge.from, to: edge.to, toward: end };
    draw();
    if (focus) focusSelected();
    if (!say) return;
    const back = other(edge, end);
    const onward = edgesAt(end).length - 1;
    const next = onward > 0 ? `${onward} more edge${onward > 1 ? "s" : ""} at node ${end}` : `node ${end} is a dead end`;
    announce(`Edge from node ${back} to node ${end} selected (${edge.kind}, ${edge.length_m.toFixed(1)} m; ${next}).${more ? " " + more : ""} Delete removes it.`);
  }

  // The turn from the way a→b to the way b→c, radians (0: straight on).
  function turn(a, b, c) {
    const [ax, az] = position(a), [bx, bz] = position(b), [cx, cz] = position(c);
    const h1 = Math.atan2(bz - az, bx - ax), h2 = Math.atan2(cz - bz, cx - bx);
    let d = Math.abs(h2 - h1) % (2 * Math.PI);
    if (d > Math.PI) d = 2 * Math.PI - d;
    return (bx === ax && bz === az) || (cx === bx && cz === bz) ? Math.PI / 2 : d;
  }

  function onFloor(id) { const n = node(id); return !!n && n.floor === state.floor; }

  // ] (step 1): the next edge along the corridor, on through the selected edge's far node, the
  // straightest way; [ (step −1): the one before it, back through its near node. From a node:
  // its first (]) or last ([) edge, going away from it.
  function alongCorridor(step) {
    const s = state.selected;
    if (!s) { announce("Select a node or an edge first."); return; }
    if (s.type === "node") {
      const around = edgesAt(s.id).filter((e) => onFloor(other(e, s.id)));
      if (!around.length) { announce(`Node ${s.id} has no edge on this floor.`); return; }
      const e = step > 0 ? around[0] : around[around.length - 1];
      selectEdge(e.from, e.to, { toward: other(e, s.id) });
      return;
    }
    const current = findEdge(s.from, s.to);
    const v = s.toward, u = other(current, v);
    const pivot = step > 0 ? v : u;
    const candidates = edgesAt(pivot).filter((e) => e !== current && onFloor(other(e, pivot)));
    if (!candidates.length) {
      announce(`Node ${pivot} is a dead end: no edge ${step > 0 ? "after" : "before"} this one along the corridor.`);
      return;
    }
    const cost = (e) => (step > 0 ? turn(u, v, other(e, v)) : turn(other(e, u), u, v));
    const best = candidates.reduce((a, b) => (cost(b) < cost(a) ? b : a));
    const others = candidates.length - 1;
    const more = others ? `Node ${pivot} is a junction: ${others} other way${others > 1 ? "s" : ""} ({ and } turn around it).` : "";
    selectEdge(best.from, best.to, { toward: step > 0 ? other(best, v) : u, more });
  }

  // { and }: the edges around the node the selected edge starts from (or the selected node), in
  // turn.
  function aroundNode(step) {
    const s = state.selected;
    const id = s && s.type === "node" ? s.id : s && s.type === "edge" ? other(findEdge(s.from, s.to), s.toward) : null;
    if (id === null) { announce("Select a node first."); return; }
    const around = edgesAt(id).filter((e) => onFloor(other(e, id)));
    if (!around.length) { announce(`Node ${id} has no edge.`); return; }
    let k = -1;
    if (s.type === "edge") k = around.findIndex((e) => e.from === s.from && e.to === s.to);
    const next = around[(k + step + around.length) % around.length];
    selectEdge(next.from, next.to, { toward: other(next, id) });
  }

  // ------------------------------------------------------------------ the operations

  function selectedNode() {
    if (!state.selected || state.selected.type !== "node") {
      announce("Select a node first.");
      return null;
    }
    return node(state.selected.id);
  }

  function quiet() {
    const n = selectedNode();
    if (n) sendEdit({ op: "quiet", at: point(n) }, `Quiet node ${n.id}`);
  }

  // C (or the toolbar's button): connect from the selected node; the focus goes to it, so that
  // the next node is one Tab or click away.
  function startConnect(focus = true) {
    const n = selectedNode();
    if (!n) return;
    state.connectFrom = n.id;
    draw();
    if (focus) focusSelected();
    announce(`Connecting from node ${n.id}: select another node, then press Enter (or click it). Escape cancels.`);
  }

  // Connect; then the new edge is selected, and focused where the focus was in the graph (a
  // click, the toolbar: the graph), so that Enter, Delete, [ and ] work on at once.
  function connectTo(id) {
    const from = node(state.connectFrom);
    const to = node(id);
    const kind = kindSelect.value;
    const inTables = document.getElementById("editor-tables").contains(document.activeElement);
    sendEdit({ op: "add_edge", from: point(from), to: point(to), kind }, `Connect node ${from.id} to node ${to.id} (${kind})`, {
      then: () => {
        const edge = findEdge(from.id, to.id);
        if (!edge) return "";
        state.selected = { type: "edge", from: edge.from, to: edge.to, toward: to.id };
        draw();
        if (!inTables) focusSelected();
        return `The new edge is selected: ${edgeName(edge, to.id)}.`;
      },
    });
  }

  // The applied add-edge edit that made the edge between nodes a and b, if any: its two ends
  // land on a and b (the nearest nodes of the edit's points, as the server anchors them).
  function addEditOf(a, b) {
    const nearest = (p) => {
      let best = null, bestD = Infinity;
      state.data.nodes.forEach((n) => {
        if (Math.abs(n.y - p[1]) > 1.5) return;
        const d = Math.hypot(n.x - p[0], n.z - p[2]);
        if (d < bestD) { best = n.id; bestD = d; }
      });
      return best;
    };
    const made = state.data.edits.slice().reverse().find((entry) => {
      if (entry.edit.op !== "add_edge" || !entry.applied) return false;
      const ends = [nearest(entry.edit.from), nearest(entry.edit.to)];
      return (ends[0] === a && ends[1] === b) || (ends[0] === b && ends[1] === a);
    });
    return made || null;
  }

  // Delete: an edge an edit of the list added is taken out by deleting that edit (not by a
  // second edit that removes it); any other edge by a remove-edge edit.
  function removeEdge() {
    if (state.busy) { startBusy(); return; }
    if (!state.selected || state.selected.type !== "edge") { announce("Select an edge first."); return; }
    const toward = state.selected.toward === undefined ? state.selected.to : state.selected.toward;
    const b = node(toward), a = node(toward === state.selected.to ? state.selected.from : state.selected.to);
    const made = addEditOf(a.id, b.id);
    state.selected = { type: "node", id: a.id };
    if (made) {
      deleteEdit(made.id, made.edit, {
        said: `Removed the edge from node ${a.id} to node ${b.id}: edit ${made.id}, which added it, is deleted. Node ${a.id} is selected.`,
      });
      return;
    }
    sendEdit({ op: "remove_edge", from: point(a), to: point(b) }, `Remove the edge from node ${a.id} to node ${b.id}`, {
      then: () => `Node ${a.id} is selected.`,
    });
  }

  function nudge(dx, dz) {
    const n = selectedNode();
    if (!n) return;
    const [x, z] = position(n.id);
    state.pending = { id: n.id, x: x + dx, z: z + dz };
    draw();
    announce(`Node ${n.id} to ${shown(state.pending.x, state.pending.z)}: Enter keeps it, Escape cancels.`);
  }

  function commitMove() {
    const pending = state.pending;
    if (!pending) return;
    const n = node(pending.id);
    sendEdit({ op: "move_node", from: point(n), to: [fixed(pending.x), fixed(n.y), fixed(pending.z)] }, `Move node ${n.id}`);
  }

  function selectedPlace() {
    if (state.selected && state.selected.type === "node") {
      const n = node(state.selected.id);
      return [fixed(n.x), fixed(n.y), fixed(n.z)];
    }
    if (state.place) return [fixed(state.place.x), fixed(level()), fixed(state.place.z)];
    return null;
  }

  function addPoi() {
    const name = document.getElementById("poi-name").value.trim();
    const at = selectedPlace();
    if (!name) { announce("Type the point of interest's name first."); document.getElementById("poi-name").focus(); return; }
    if (!at) { announce("Select a node or click a place on the map first."); return; }
    sendEdit({ op: "add_poi", name, at }, `Add point of interest ${name}`);
  }

  function renamePoi() {
    const name = document.getElementById("poi-existing").value;
    const newName = document.getElementById("poi-name").value.trim();
    if (!name || !newName) { announce("Choose a point of interest and type its new name."); return; }
    sendEdit({ op: "rename_poi", name, new_name: newName }, `Rename ${name} to ${newName}`);
  }

  function removePoi() {
    const name = document.getElementById("poi-existing").value;
    if (!name) { announce("Choose a point of interest."); return; }
    sendEdit({ op: "remove_poi", name }, `Remove point of interest ${name}`);
  }

  function cancel() {
    if (state.pending) { state.pending = null; draw(); announce("Move canceled."); return; }
    if (state.connectFrom !== null) { state.connectFrom = null; draw(); announce("Connecting canceled."); return; }
    state.selected = null;
    draw();
    announce("Nothing selected.");
  }

  function zoom(factor, sx = W / 2, sy = H / 2) {
    const [x, z] = toMap(sx, sy);
    state.view.scale = Math.min(Math.max(state.view.scale * factor, 0.5), 400);
    const [x2, z2] = toMap(sx, sy);
    state.view.cx += x - x2;
    state.view.cz += z - z2;
    draw();
  }

  function pan(dxScreen, dyScreen) {
    state.view.cx -= dxScreen / state.view.scale;
    state.view.cz -= dyScreen / state.view.scale;
    draw();
  }

  // ------------------------------------------------------------------ the mouse

  function nodePointerDown(event, id) {
    event.stopPropagation();
    event.preventDefault();
    if (state.connectFrom !== null && state.connectFrom !== id) {
      connectTo(id);
      return;
    }
    const [sx, sy] = pointerToSvg(event);
    state.drag = { kind: "node", id, sx, sy, moved: false };
    canvas.setPointerCapture(event.pointerId);
    selectNode(id);
  }

  canvas.addEventListener("pointerdown", (event) => {
    const [sx, sy] = pointerToSvg(event);
    state.drag = { kind: "pan", sx, sy, moved: false };
    canvas.setPointerCapture(event.pointerId);
  });

  canvas.addEventListener("pointermove", (event) => {
    const drag = state.drag;
    if (!drag) return;
    const [sx, sy] = pointerToSvg(event);
    if (!drag.moved && Math.hypot(sx - drag.sx, sy - drag.sy) < 4) return;
    drag.moved = true;
    if (drag.kind === "node") {
      const [x, z] = toMap(sx, sy);
      state.pending = { id: drag.id, x, z };
      draw();
    } else {
      pan(sx - drag.sx, sy - drag.sy);
      drag.sx = sx;
      drag.sy = sy;
    }
  });

  canvas.addEventListener("pointerup", (event) => {
    const drag = state.drag;
    state.drag = null;
    if (!drag) return;
    if (drag.kind === "node" && drag.moved) {
      commitMove();
    } else if (drag.kind === "pan" && !drag.moved) {
      const [x, z] = toMap(...pointerToSvg(event));
      state.place = { x, z };
      state.selected = null;
      draw();
      announce(`Place chosen at ${shown(x, z)}.`);
    }
  });

  canvas.addEventListener("wheel", (event) => {
    event.preventDefault();
    const [sx, sy] = pointerToSvg(event);
    zoom(event.deltaY < 0 ? 1.2 : 1 / 1.2, sx, sy);
  }, { passive: false });

  // ------------------------------------------------------------------ the keyboard

  canvas.addEventListener("keydown", (event) => {
    const key = event.key;
    const step = event.shiftKey ? FINE_STEP_M : MOVE_STEP_M;
    const onNode = state.selected && state.selected.type === "node";
    const onEdge = state.selected && state.selected.type === "edge";
    let handled = true;
    if ((event.ctrlKey || event.metaKey) && key.toLowerCase() === "z") undo();
    else if (event.ctrlKey || event.metaKey || event.altKey) handled = false;
    else if (key === "q" || key === "Q") quiet();
    else if (key === "c" || key === "C") startConnect();
    else if (key === "u" || key === "U") undo();
    else if (key === "p" || key === "P") document.getElementById("poi-name").focus();
    else if (key === "Delete" || key === "Backspace") removeEdge();
    else if (key === "[") alongCorridor(-1);
    else if (key === "]") alongCorridor(1);
    else if (key === "{") aroundNode(-1);
    else if (key === "}") aroundNode(1);
    else if (key === "+" || key === "=") zoom(1.25);
    else if (key === "-" || key === "_") zoom(1 / 1.25);
    else if (key === "0") { fit(); draw(); }
    else if (key === "Escape") cancel();
    else if (key === "Enter" || key === " ") {
      if (state.pending) commitMove();
      else if (state.connectFrom !== null && onNode && state.selected.id !== state.connectFrom) connectTo(state.selected.id);
      else if (event.target.dataset && event.target.dataset.edge !== undefined && !onEdge) {
        const [from, to] = event.target.dataset.edge.split("-").map(Number);
        selectEdge(from, to);
      } else if (event.target.dataset && event.target.dataset.node !== undefined && !onNode) {
        selectNode(Number(event.target.dataset.node));
      } else if (onNode) selectNode(state.selected.id);
      else if (onEdge) selectEdge(state.selected.from, state.selected.to, { toward: state.selected.toward });
      else handled = false;
    } else if (key.startsWith("Arrow")) {
      const dx = key === "ArrowLeft" ? -1 : key === "ArrowRight" ? 1 : 0;
      const dz = key === "ArrowUp" ? -1 : key === "ArrowDown" ? 1 : 0;
      if (onNode) nudge(dx * step, dz * step);
      else pan(-dx * 40, -dz * 40);
    } else handled = false;
    if (handled) event.preventDefault();
  });

  // Ctrl+Z anywhere in the editor but a text field (the graph has its own keys, above): from the
  // tables' and the forms' buttons too.
  root.addEventListener("keydown", (event) => {
    if (!(event.ctrlKey || event.metaKey) || event.key.toLowerCase() !== "z" || event.shiftKey) return;
    const target = event.target;
    if (canvas.contains(target) || target.matches("input, textarea, select, [contenteditable]")) return;
    event.preventDefault();
    undo();
  });

  // ------------------------------------------------------------------ the controls

  const actions = {
    "zoom-in": () => zoom(1.25),
    "zoom-out": () => zoom(1 / 1.25),
    fit: () => { fit(); draw(); },
    quiet,
    connect: startConnect,
    "remove-edge": removeEdge,
    undo,
    "add-poi": addPoi,
    "rename-poi": renamePoi,
    "remove-poi": removePoi,
  };
  root.addEventListener("click", (event) => {
    const button = event.target.closest("[data-action]");
    if (button && actions[button.dataset.action]) {
      event.preventDefault();
      actions[button.dataset.action]();
    }
  });

  floorSelect.addEventListener("change", () => {
    state.floor = Number(floorSelect.value);
    state.selected = null;
    state.pending = null;
    fit();
    draw();
    announce(`${floorSelect.options[floorSelect.selectedIndex].text} shown.`);
  });

  // The page's first Tab stop leads here: to the selected node or edge, else the first node.
  const skip = document.getElementById("skip-to-graph");
  if (skip) {
    skip.addEventListener("click", (event) => {
      if (!state.data) return;
      event.preventDefault();
      if (focusSelected()) return;
      const first = canvas.querySelector("[data-node]");
      if (first) first.focus({ preventScroll: false });
      else canvas.focus();
    });
  }

  // ------------------------------------------------------------------ the route tester

  async function planRoute(announceIt) {
    const from = document.getElementById("editor-from").value;
    const to = document.getElementById("editor-to").value;
    const summary = document.getElementById("editor-route-summary");
    const steps = document.getElementById("editor-steps");
    if (!from || !to || (!announceIt && !state.route && !steps.children.length)) return;
    try {
      const query = new URLSearchParams({ from, to });
      const route = await request("GET", `${base}/route?${query}`);
      state.route = route;
      summary.textContent = `${route.length_m.toFixed(1)} m, ${route.steps.length} steps.`;
      steps.replaceChildren(...route.steps.map((s) => {
        const item = document.createElement("li");
        item.textContent = s.instruction;
        return item;
      }));
      if (announceIt) announce(`Route planned: ${route.steps.map((s) => s.instruction).join("; ")}.`);
    } catch (error) {
      state.route = null;
      summary.textContent = error.message;
      steps.replaceChildren();
    }
    draw();
  }

  document.getElementById("editor-route-form").addEventListener("submit", (event) => {
    event.preventDefault();
    planRoute(true);
  });

  load().then(() => {
    root.dataset.ready = "true";
    const floorNodes = state.data.nodes.filter((n) => n.floor === state.floor).length;
    announce(`Graph loaded: ${floorNodes} nodes on ${floorSelect.options[floorSelect.selectedIndex].text}. Tab to a node or an edge to select it, or use the tables below the map.`);
  }).catch((error) => showError(`The graph could not be loaded: ${error.message}`));
})();
