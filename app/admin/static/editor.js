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
    selected: null, // {type: "node", id} | {type: "edge", from, to}
    pending: null, // {id, x, z}: a move not sent yet
    connectFrom: null, // a node id
    place: null, // {x, z}: the background point clicked last
    undo: [],
    drag: null,
    busy: false,
  };

  // ------------------------------------------------------------------ helpers

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

  // Send an edit; remember how to undo it (unless it is an undo itself).
  async function sendEdit(edit, description, { remember = true } = {}) {
    if (!startBusy()) return;
    showError("");
    try {
      const answer = await request("POST", `${base}/edits`, edit);
      if (remember) state.undo.push({ kind: "added", id: answer.id, description });
      state.pending = null;
      state.connectFrom = null;
      await load();
      announce(`${description}: done (edit ${answer.id}).`);
      await planRoute(false);
    } catch (error) {
      showError(`${description}: ${error.message}`);
      announce(`${description} refused: ${error.message}`);
    } finally {
      endBusy();
    }
  }

  async function deleteEdit(id, edit, { remember = true } = {}) {
    if (!startBusy()) return;
    showError("");
    try {
      await request("DELETE", `${base}/edits/${id}`);
      if (remember) state.undo.push({ kind: "deleted", edit, description: describe(edit) });
      await load();
      announce(`Edit ${id} deleted.`);
      await planRoute(false);
    } catch (error) {
      showError(`Deleting edit ${id}: ${error.message}`);
      announce(`Deleting edit ${id} failed: ${error.message}`);
    } finally {
      endBusy();
    }
  }

  async function undo() {
    const last = state.undo.pop();
    if (!last) { announce("Nothing to undo."); return; }
    if (last.kind === "added") {
      await deleteEdit(last.id, null, { remember: false });
      announce(`Undone: ${last.description}.`);
    } else {
      await sendEdit(last.edit, `Undo the deletion of ${last.description}`, { remember: false });
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

  function draw() {
    const data = state.data;
    const focusedId = document.activeElement && document.activeElement.dataset
      ? document.activeElement.dataset.node : undefined;
    canvas.replaceChildren();
    const floorNodes = data.nodes.filter((n) => n.floor === state.floor);
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
    // edges: a visible line and a wide one to click
    const edgeLayer = el("g", { class: "edges" }, canvas);
    data.edges.forEach((edge) => {
      const a = here.has(edge.from), b = here.has(edge.to);
      if (!a && !b) return;
      const [x1, y1] = toScreen(...position(a ? edge.from : edge.to));
      let [x2, y2] = toScreen(...position(b ? edge.to : edge.from));
      if (!(a && b)) { x2 += 14; y2 -= 14; } // a floor change: a stub toward the other floor
      const selected = state.selected && state.selected.type === "edge"
        && state.selected.from === edge.from && state.selected.to === edge.to;
      el("line", { x1, y1, x2, y2, class: `edge edge-${edge.kind}${selected ? " selected" : ""}` }, edgeLayer);
      const hit = el("line", { x1, y1, x2, y2, class: "edge-hit", "data-from": edge.from, "data-to": edge.to }, edgeLayer);
      hit.addEventListener("pointerdown", (event) => {
        event.stopPropagation();
        selectEdge(edge.from, edge.to);
      });
    });
    // tags and points of interest
    data.tags.filter((t) => t.floor === state.floor).forEach((tag) => {
      const [sx, sy] = toScreen(tag.x, tag.z);
      el("rect", { x: sx - 4, y: sy - 4, width: 8, height: 8, class: "tag", "aria-hidden": "true" }, canvas);
      const label = el("text", { x: sx + 6, y: sy - 6, class: "tag-label", "aria-hidden": "true" }, canvas);
      label.textContent = String(tag.id);
    });
    data.pois.filter((p) => p.floor === state.floor).forEach((poi) => {
      const [sx, sy] = toScreen(poi.x, poi.z);
      el("path", { d: `M${sx} ${sy - 7}L${sx + 7} ${sy}L${sx} ${sy + 7}L${sx - 7} ${sy}Z`, class: "poi", "aria-hidden": "true" }, canvas);
      const label = el("text", { x: sx + 9, y: sy + 4, class: "poi-label", "aria-hidden": "true" }, canvas);
      label.textContent = poi.name;
    });
    // the place clicked
    if (state.place) {
      const [sx, sy] = toScreen(state.place.x, state.place.z);
      el("path", { d: `M${sx - 6} ${sy}H${sx + 6}M${sx} ${sy - 6}V${sy + 6}`, class: "place", "aria-hidden": "true" }, canvas);
    }
    // nodes: focusable buttons
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
        "aria-label": `Node ${n.id}, ${n.kind}${n.quiet ? ", quiet" : ""}, ${shown(n.x, n.z)}`,
        "data-node": String(n.id),
      }, nodeLayer);
      circle.addEventListener("pointerdown", (event) => nodePointerDown(event, n.id));
      circle.addEventListener("focus", () => {
        if (!(state.selected && state.selected.type === "node" && state.selected.id === n.id)) selectNode(n.id, false);
      });
    });
    if (focusedId !== undefined) {
      const again = canvas.querySelector(`[data-node="${focusedId}"]`);
      if (again) again.focus({ preventScroll: true });
    }
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

  function selectNode(id, focus = true) {
    state.selected = { type: "node", id };
    const n = node(id);
    draw();
    if (focus) {
      const circle = canvas.querySelector(`[data-node="${id}"]`);
      if (circle) circle.focus({ preventScroll: true });
    }
    const joining = state.connectFrom !== null && state.connectFrom !== id
      ? ` Press Enter to connect node ${state.connectFrom} to it.` : "";
    announce(`Node ${id} selected, ${n.kind}${n.quiet ? ", quiet" : ""}, ${shown(n.x, n.z)}.${joining}`);
  }

  function selectEdge(from, to) {
    state.selected = { type: "edge", from, to };
    const edge = state.data.edges.find((e) => e.from === from && e.to === to);
    draw();
    canvas.focus({ preventScroll: true });
    announce(`Edge from node ${from} to node ${to} selected (${edge ? edge.kind : "edge"}, ${edge ? edge.length_m.toFixed(1) : "?"} m). Delete removes it.`);
  }

  function cycleEdge(step) {
    const id = state.selected && state.selected.type === "node" ? state.selected.id
      : state.selected && state.selected.type === "edge" ? state.selected.from : null;
    if (id === null) { announce("Select a node first."); return; }
    const around = state.data.edges.filter((e) => e.from === id || e.to === id);
    if (!around.length) { announce(`Node ${id} has no edge.`); return; }
    let k = -1;
    if (state.selected.type === "edge") {
      k = around.findIndex((e) => e.from === state.selected.from && e.to === state.selected.to);
    }
    const next = around[(k + step + around.length) % around.length];
    selectEdge(next.from, next.to);
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

  function startConnect() {
    const n = selectedNode();
    if (!n) return;
    state.connectFrom = n.id;
    draw();
    announce(`Connecting from node ${n.id}: select another node, then press Enter (or click it). Escape cancels.`);
  }

  function connectTo(id) {
    const from = node(state.connectFrom);
    const to = node(id);
    const kind = kindSelect.value;
    sendEdit({ op: "add_edge", from: point(from), to: point(to), kind }, `Connect node ${from.id} to node ${to.id} (${kind})`);
  }

  function removeEdge() {
    if (!state.selected || state.selected.type !== "edge") { announce("Select an edge first."); return; }
    const a = node(state.selected.from), b = node(state.selected.to);
    state.selected = null;
    sendEdit({ op: "remove_edge", from: point(a), to: point(b) }, `Remove the edge from node ${a.id} to node ${b.id}`);
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
    let handled = true;
    if ((event.ctrlKey || event.metaKey) && key.toLowerCase() === "z") undo();
    else if (event.ctrlKey || event.metaKey || event.altKey) handled = false;
    else if (key === "q" || key === "Q") quiet();
    else if (key === "c" || key === "C") startConnect();
    else if (key === "u" || key === "U") undo();
    else if (key === "p" || key === "P") document.getElementById("poi-name").focus();
    else if (key === "Delete" || key === "Backspace") removeEdge();
    else if (key === "[") cycleEdge(-1);
    else if (key === "]") cycleEdge(1);
    else if (key === "+" || key === "=") zoom(1.25);
    else if (key === "-" || key === "_") zoom(1 / 1.25);
    else if (key === "0") { fit(); draw(); }
    else if (key === "Escape") cancel();
    else if (key === "Enter" || key === " ") {
      if (state.pending) commitMove();
      else if (state.connectFrom !== null && onNode && state.selected.id !== state.connectFrom) connectTo(state.selected.id);
      else if (onNode) selectNode(state.selected.id);
      else handled = false;
    } else if (key.startsWith("Arrow")) {
      const dx = key === "ArrowLeft" ? -1 : key === "ArrowRight" ? 1 : 0;
      const dz = key === "ArrowUp" ? -1 : key === "ArrowDown" ? 1 : 0;
      if (onNode) nudge(dx * step, dz * step);
      else pan(-dx * 40, -dz * 40);
    } else handled = false;
    if (handled) event.preventDefault();
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
    announce("Graph loaded: tab to a node to select it.");
  }).catch((error) => showError(`The graph could not be loaded: ${error.message}`));
})();
