// mocapd view: the page. Vanilla JS, no build step. Everything that comes from the bus is shown
// as text (textContent, attributes through the DOM), never parsed as HTML.
// What it draws is recorded on window.mocapdView (for tests and figures) and in data-* attributes.
"use strict";

(() => {
  const AUTO_SPIN = 0.35; // radians a second
  const LAG_WARN_S = 1.0;
  const RESUME_SPIN_MS = 3000;
  const SHOWN_DETECTIONS = 20;
  const PROGRESS_SLOTS = 6; // rows of classes under way a card keeps
  const MAX_TICKS = 16; // keyframes drawn as ticks; more are said as k/n only
  const NEAR_LEVEL = 0.95; // a bar this full is drawn as nearly complete
  const STILL_MS = 3000; // a row unchanged this long is greyed
  const STRIP_S = 30;
  const SHOWN_REFUSED = 50;
  const LATENCIES_KEPT = 4000;
  const LEFT = new Set(["lhip", "lknee", "lankle", "ltoes", "lclavicle", "lshoulder", "lelbow", "lwrist", "lfingers", "lthumb"]);
  const RIGHT = new Set(["rhip", "rknee", "rankle", "rtoes", "rclavicle", "rshoulder", "relbow", "rwrist", "rfingers", "rthumb"]);

  // A camera looking at (cx, cy, cz) from `depth` away, turned by `yaw` about the vertical and
  // tilted down by `pitch`, scale px/mm, the screen w × h. The world is right-handed with y up, so
  // before turning the camera sits on +z looking toward -z: +x is the screen's right, and a point
  // nearer the camera (larger z) is drawn larger. Returns (x, y, z) mm -> [u, v] px.
  function projection(cam) {
    const cosY = Math.cos(cam.yaw);
    const sinY = Math.sin(cam.yaw);
    const cosP = Math.cos(cam.pitch);
    const sinP = Math.sin(cam.pitch);
    return (x, y, z) => {
      const dx = x - cam.cx;
      const dy = y - cam.cy;
      const dz = z - cam.cz;
      const x1 = dx * cosY + dz * sinY;
      const z1 = -dx * sinY + dz * cosY;
      const y2 = dy * cosP - z1 * sinP;
      const z2 = dy * sinP + z1 * cosP; // toward the camera
      const s = (cam.scale * cam.depth) / Math.max(cam.depth - z2, 0.05 * cam.depth);
      return [cam.w / 2 + x1 * s, cam.h / 2 - y2 * s];
    };
  }

  const record = {
    projection, // for the tests: the figure's camera
    log: () => [...sessionLog.values()], // the session's detections, oldest first
    connected: false,
    snapshots: 0,
    messages: 0,
    fps: 0,
    frames: 0,
    streams: Object.create(null), // stream id -> what its card drew (a map without a prototype)
    refused: [],
    latencies() {
      return Object.values(this.streams).flatMap((s) => s.latencies);
    },
  };
  window.mocapdView = record;

  let joints = [];
  let bones = [];
  const cards = new Map();
  const daemons = new Map();
  const dismissed = new Set(); // ended streams the operator removed
  const sessionLog = new Map(); // detection id -> detection, oldest first
  const logStreams = new Set();
  const LOG_KEPT = 10000;
  const SHOWN_LOG = 200;
  const $ = (id) => document.getElementById(id);

  function el(tag, className, text) {
    const node = document.createElement(tag);
    if (className) node.className = className;
    if (text !== undefined) node.textContent = text;
    return node;
  }

  function fixed(x, digits) {
    return typeof x === "number" && Number.isFinite(x) ? x.toFixed(digits) : "–";
  }

  const MAX_DATE_MS = 8.64e15; // ECMAScript's time range: a Date past it is "Invalid Date"

  function clock(seconds) {
    const ms = typeof seconds === "number" ? seconds * 1000 : NaN;
    return Number.isFinite(ms) && Math.abs(ms) <= MAX_DATE_MS ? new Date(ms).toLocaleTimeString() : "–";
  }

  // ------------------------------------------------------------------------------ a stream's card

  class Card {
    constructor(info) {
      this.id = info.stream;
      this.pose = null;
      this.drawnSeq = null;
      this.yaw = 0.6;
      this.pitch = 0.3;
      this.dragging = false;
      this.touched = -Infinity;
      this.lastDraw = 0;
      this.extent = 0;
      this.ids = new Set();
      this.progressRows = new Map();
      this.rec = {
        posesDrawn: 0,
        draws: 0,
        latencyMs: null,
        latencies: [],
        lastSeq: null,
        detections: [],
        progress: Object.create(null),
        progressUpdates: 0,
        drawn: null, // the last figure drawn: { yaw, pitch, screen: [[u, v] per joint] }
      };
      record.streams[this.id] = this.rec;

      const root = (this.root = el("section", "card"));
      root.dataset.stream = this.id;
      root.dataset.posesDrawn = "0";
      const head = el("header", "card-head");
      head.append(el("h2", "stream-id", this.id), (this.kind = el("span", "kind muted", "")));
      // an ended stream stays, greyed, with its detections until the operator dismisses it
      this.dismiss = el("button", "dismiss", "dismiss");
      this.dismiss.type = "button";
      this.dismiss.title = "the stream has ended: remove its card (its detections stay in the log)";
      this.dismiss.hidden = true;
      this.dismiss.addEventListener("click", () => {
        dismissed.add(this.id);
        gone(this.id);
      });
      head.append(this.dismiss);
      const canvas = (this.canvas = el("canvas", "figure"));
      canvas.width = 320;
      canvas.height = 260;
      this.ctx = canvas.getContext("2d");
      const stats = el("div", "stats");
      this.rate = el("span", "stat", "– poses/s");
      this.lag = el("span", "stat", "lag –");
      this.missing = el("span", "stat", "missing 0");
      this.latency = el("span", "stat", "on screen –");
      stats.append(this.rate, this.lag, this.missing, this.latency);
      this.progress = el("div", "progress");
      // until a progress message comes, the daemon may not publish any (it does with --progress)
      this.progress.append((this.idle = el("p", "muted small", "no progress yet (mocapd run --progress)")));
      this.more = el("p", "muted small more", "");
      this.progress.append(this.more);
      const timelineHead = el("h3", "small", "Detections");
      this.timeline = el("ol", "timeline");
      root.append(head, canvas, stats, el("h3", "small", "Under way"), this.progress, timelineHead, this.timeline);
      this.update(info);
      this.orbit();
    }

    update(info) {
      this.hz = info.rate;
      const kind = info.kind ? `${info.kind}` : "no skeleton yet";
      const rate = typeof info.rate === "number" ? ` · ${fixed(info.rate, 0)} Hz` : "";
      this.kind.textContent = kind + rate;
      this.setEnded(info.ended === true);
    }

    setEnded(ended) {
      this.ended = ended;
      this.root.classList.toggle("ended", ended);
      this.root.dataset.ended = String(ended);
      this.dismiss.hidden = !ended;
      if (ended) this.kind.textContent = `${this.kind.textContent.replace(/ · ended$/, "")} · ended`;
    }

    orbit() {
      const c = this.canvas;
      let x = 0;
      let y = 0;
      c.addEventListener("pointerdown", (e) => {
        this.dragging = true;
        x = e.clientX;
        y = e.clientY;
        c.setPointerCapture(e.pointerId);
      });
      c.addEventListener("pointermove", (e) => {
        if (!this.dragging) return;
        this.yaw += (e.clientX - x) * 0.01;
        this.pitch = Math.max(-1.2, Math.min(1.2, this.pitch + (e.clientY - y) * 0.01));
        x = e.clientX;
        y = e.clientY;
        this.touched = performance.now();
      });
      const release = () => {
        this.dragging = false;
        this.touched = performance.now();
      };
      c.addEventListener("pointerup", release);
      c.addEventListener("pointercancel", release);
    }

    setPose(p) {
      if (Array.isArray(p.p) && p.p.length === joints.length * 3) this.pose = p;
    }

    setStats(s) {
      this.rate.textContent = `${fixed(s.rate, 0)} poses/s`;
      this.lag.textContent = `lag ${s.lag === null ? "–" : fixed(s.lag * 1000, 0) + " ms"}`;
      this.lag.classList.toggle("warn", s.lag !== null && s.lag > LAG_WARN_S);
      this.lag.title = s.lag !== null && s.lag > LAG_WARN_S ? "the poses arrive over a second late" : "";
      // the relay's thinning (zmq.relay_per_s) is not the publisher's loss: shown apart
      const sampled = s.sampled > 1 ? ` · sampled 1 in ${s.sampled}` : "";
      this.missing.textContent = `missing ${s.missing}${sampled}`;
      const latency = this.rec.latencyMs === null ? "–" : `${fixed(this.rec.latencyMs, 0)} ms`;
      this.latency.textContent = `on screen ${latency} after the pose`;
      this.missing.classList.toggle("warn", s.missing > 0);
      this.root.dataset.rate = String(s.rate);
      this.root.dataset.missing = String(s.missing);
      this.root.dataset.sampled = String(s.sampled);
      this.root.dataset.posesDrawn = String(this.rec.posesDrawn);
      if (this.rec.latencyMs !== null) this.root.dataset.latencyMs = String(Math.round(this.rec.latencyMs));
    }

    // Progress rows: at most PROGRESS_SLOTS, each kept in its place once made (nothing jumps); a
    // class no longer under way stays, at zero and grey, until a new class needs its slot (the
    // one idle longest gives it up). The bar is the server's `level`, position × (1 − cost/τ):
    // it is full only for a match that reaches the template's end well within τ, so a class that
    // merely sits near the end of a loose template is not drawn as nearly complete. Keyframes
    // matched are apart from it (ticks, k of n); the strip under them is the last 30 s of the
    // level, with the class's detections marked.
    setProgress(ev) {
      this.rec.progressUpdates += 1;
      const now = performance.now();
      const rec = Object.create(null);
      const listed = new Map(ev.classes.map((c) => [c.class, c]));
      // the nearest first, so that when slots are short the classes nearest a detection get them
      const nearest = [...ev.classes].sort((a, b) => (b.level ?? 0) - (a.level ?? 0));
      for (const c of nearest) if (!this.progressRows.has(c.class)) this.claimRow(c.class, c.level ?? 0, listed, now);
      let hidden = 0;
      for (const c of ev.classes) if (!this.progressRows.has(c.class)) hidden += 1;
      for (const [name, row] of this.progressRows) {
        const c = listed.get(name);
        const n = c ? c.keyframes : row.keyframes;
        const k = c ? c.matched.length : 0;
        const level = c ? (typeof c.level === "number" ? c.level : 0) : 0;
        if (n !== row.keyframes) {
          row.keyframes = n;
          row.ticks.replaceChildren();
          if (n <= MAX_TICKS) for (let i = 0; i < n; i++) row.ticks.append(el("span", "tick"));
        }
        if (n <= MAX_TICKS) Array.from(row.ticks.children).forEach((t, i) => t.classList.toggle("on", i < k));
        row.keys.textContent = n ? `${k}/${n} keyframes` : "no keyframes";
        if (level !== row.level || k !== row.matched) row.changed = now;
        row.level = level;
        row.matched = k;
        row.fill.style.width = `${Math.round(level * 1000) / 10}%`;
        row.root.classList.toggle("near", level >= NEAR_LEVEL);
        row.cost.textContent = c ? `cost ${fixed(c.cost, 3)} / τ ${fixed(c.tau, 3)}` : "not under way";
        row.cost.classList.toggle("ok", c !== undefined && c.cost < c.tau && c.position > 0);
        row.root.dataset.position = String(c ? c.position : 0);
        row.root.dataset.level = String(level);
        row.root.dataset.matched = String(k);
        row.root.dataset.keyframes = String(n);
        row.root.dataset.cost = String(c ? c.cost : "");
        row.history.push([ev.frame, level]);
        while (row.history.length > 1 && row.history[0][0] < ev.frame - this.stripFrames()) row.history.shift();
        if (c) rec[name] = { position: c.position, level, matched: k, keyframes: n, cost: c.cost, tau: c.tau };
        this.drawStrip(row, ev.frame);
      }
      this.lastFrame = ev.frame;
      this.more.textContent = hidden ? `+${hidden} more under way` : "";
      this.rec.progress = rec;
      this.rec.progressHidden = hidden;
      this.idle.textContent = "no motion under way";
      this.idle.hidden = ev.classes.length > 0;
      this.greyRows(now);
    }

    stripFrames() {
      return STRIP_S * (typeof this.hz === "number" && this.hz > 0 ? this.hz : 120);
    }

    // a slot for `name` (at `level`): a free one, else that of the class idle longest (not under
    // way now), else that of the farthest class under way if it is farther than `name` and has
    // not changed for a second (no two classes take one slot in turn every message)
    claimRow(name, level, listed, now) {
      if (this.progressRows.size >= PROGRESS_SLOTS) {
        let oldest = null;
        for (const [other, row] of this.progressRows) {
          if (!listed.has(other) && (oldest === null || row.changed < oldest[1].changed)) {
            oldest = [other, row];
          }
        }
        for (const [other, row] of oldest === null ? this.progressRows : []) {
          const farther = row.level < level && now - row.changed > 1000;
          if (farther && (oldest === null || row.level < oldest[1].level)) oldest = [other, row];
        }
        if (oldest === null) return;
        const [other, row] = oldest;
        this.progressRows.delete(other);
        this.resetRow(row, name, now);
        this.progressRows.set(name, row);
        return;
      }
      const row = this.progressRow(name);
      this.resetRow(row, name, now);
      this.progressRows.set(name, row);
      this.progress.insertBefore(row.root, this.more);
    }

    resetRow(row, name, now) {
      row.root.dataset.class = name;
      row.name.textContent = name;
      row.history = [];
      row.spans = [];
      row.level = 0;
      row.matched = 0;
      row.keyframes = -1;
      row.changed = now;
    }

    greyRows(now) {
      for (const row of this.progressRows.values()) {
        row.root.classList.toggle("still", row.level === 0 || now - row.changed > STILL_MS);
      }
    }

    drawStrip(row, frame) {
      const ctx = row.strip.getContext("2d");
      const w = row.strip.width;
      const h = row.strip.height;
      const span = this.stripFrames();
      const x = (f) => w - ((frame - f) / span) * w;
      ctx.clearRect(0, 0, w, h);
      ctx.fillStyle = "#2e7d4f";
      for (const [a, b] of row.spans) if (b >= frame - span) ctx.fillRect(x(a), 0, Math.max(2, x(b) - x(a)), h);
      ctx.strokeStyle = "#8ab4f8";
      ctx.beginPath();
      row.history.forEach(([f, level], i) => {
        const y = h - 1 - level * (h - 2);
        if (i === 0) ctx.moveTo(x(f), y);
        else ctx.lineTo(x(f), y);
      });
      ctx.stroke();
    }

    progressRow(name) {
      const root = el("div", "class-progress");
      root.dataset.class = name;
      const label = el("div", "class-head");
      const keys = el("span", "keys muted small");
      const nameEl = el("span", "class-name", name);
      label.append(nameEl, keys);
      const bar = el("div", "bar");
      const fill = el("div", "fill");
      bar.append(fill);
      const ticks = el("div", "ticks");
      const cost = el("span", "cost small");
      const foot = el("div", "class-foot");
      foot.append(ticks, cost);
      const strip = el("canvas", "strip");
      strip.width = 280;
      strip.height = 14;
      strip.title = "the last 30 s: the bar's level, and this class's detections (green)";
      root.append(label, bar, foot, strip);
      return { root, keys, name: nameEl, fill, ticks, cost, strip, history: [], spans: [], level: 0, matched: 0, keyframes: -1, changed: 0 };
    }

    addDetection(d) {
      if (this.ids.has(d.id)) return;
      this.ids.add(d.id);
      this.rec.detections.push({ id: d.id, class: d.class, start: d.start_frame, end: d.end_frame, cost: d.cost, tau: d.tau });
      const li = el("li", "detection");
      li.dataset.class = d.class;
      li.dataset.start = String(d.start_frame);
      li.dataset.end = String(d.end_frame);
      li.dataset.id = d.id;
      li.append(
        el("span", "class-name", d.class),
        el("span", "frames", `${d.start_frame}–${d.end_frame}`),
        el("span", "cost ok small", `${fixed(d.cost, 3)} ≤ τ ${fixed(d.tau, 3)}`),
        el("time", "muted small", clock(d.emit_time)),
      );
      this.timeline.prepend(li);
      while (this.timeline.childElementCount > SHOWN_DETECTIONS) this.timeline.lastChild.remove();
      const row = this.progressRows.get(d.class);
      if (row) {
        row.spans.push([d.start_frame, d.end_frame]);
        if (row.spans.length > 64) row.spans.shift();
        if (this.lastFrame !== undefined) this.drawStrip(row, Math.max(this.lastFrame, d.end_frame));
      }
    }

    draw(now) {
      if (this.progressRows.size && now - (this.greyed || 0) > 250) {
        this.greyed = now;
        this.greyRows(now);
      }
      const spinning = !this.dragging && now - this.touched > RESUME_SPIN_MS;
      const dt = this.lastDraw ? Math.min(0.1, (now - this.lastDraw) / 1000) : 0;
      const fresh = this.pose !== null && this.pose.seq !== this.drawnSeq;
      if (spinning) this.yaw += AUTO_SPIN * dt;
      this.lastDraw = now;
      if (!fresh && !this.dragging && !(spinning && this.pose)) return;
      this.render();
      this.rec.draws += 1;
      if (fresh) {
        this.drawnSeq = this.pose.seq;
        const latency = Date.now() - this.pose.time * 1000;
        this.rec.posesDrawn += 1;
        this.rec.latencyMs = latency;
        this.rec.lastSeq = this.pose.seq;
        this.rec.latencies.push(latency);
        if (this.rec.latencies.length > LATENCIES_KEPT) this.rec.latencies.splice(0, LATENCIES_KEPT / 2);
      }
    }

    render() {
      const ctx = this.ctx;
      const w = this.canvas.width;
      const h = this.canvas.height;
      ctx.fillStyle = "#10161f";
      ctx.fillRect(0, 0, w, h);
      const p = this.pose.p;
      const n = joints.length;
      let minY = Infinity;
      let maxY = -Infinity;
      for (let j = 0; j < n; j++) {
        minY = Math.min(minY, p[3 * j + 1]);
        maxY = Math.max(maxY, p[3 * j + 1]);
      }
      this.extent = Math.max(this.extent * 0.995, maxY - minY, 500); // mm
      const cx = p[0];
      const cz = p[2];
      const cy = minY + this.extent / 2;
      const scale = (h * 0.78) / this.extent;
      const project = projection({
        cx, cy, cz, scale, w, h, yaw: this.yaw, pitch: this.pitch, depth: this.extent * 4,
      });
      // the floor under the figure: a ring of radius half its height, for depth
      ctx.strokeStyle = "#2a3646";
      ctx.lineWidth = 1;
      ctx.beginPath();
      for (let i = 0; i <= 48; i++) {
        const a = (i / 48) * 2 * Math.PI;
        const r = this.extent * 0.5;
        const [u, v] = project(cx + r * Math.cos(a), minY, cz + r * Math.sin(a));
        if (i === 0) ctx.moveTo(u, v);
        else ctx.lineTo(u, v);
      }
      ctx.stroke();
      const screen = new Array(n);
      for (let j = 0; j < n; j++) screen[j] = project(p[3 * j], p[3 * j + 1], p[3 * j + 2]);
      this.rec.drawn = { yaw: this.yaw, pitch: this.pitch, screen };
      ctx.lineWidth = 3;
      ctx.lineCap = "round";
      for (const [a, b] of bones) {
        const name = joints[b];
        ctx.strokeStyle = LEFT.has(name) ? "#5fb3ff" : RIGHT.has(name) ? "#ffb35f" : "#d7dde6";
        ctx.beginPath();
        ctx.moveTo(screen[a][0], screen[a][1]);
        ctx.lineTo(screen[b][0], screen[b][1]);
        ctx.stroke();
      }
      const head = joints.indexOf("head");
      if (head >= 0) {
        ctx.fillStyle = "#d7dde6";
        ctx.beginPath();
        ctx.arc(screen[head][0], screen[head][1], 4, 0, 2 * Math.PI);
        ctx.fill();
      }
    }

    remove() {
      this.root.remove();
      delete record.streams[this.id];
    }
  }

  // ---------------------------------------------------------------------------------- the page

  function card(info) {
    if (!info.ended) dismissed.delete(info.stream);
    let c = cards.get(info.stream);
    if (!c) {
      c = new Card(info);
      cards.set(info.stream, c);
      $("streams").append(c.root);
      $("empty").hidden = true;
    } else {
      c.update(info);
    }
    return c;
  }

  function gone(id) {
    const c = cards.get(id);
    if (c) {
      c.remove();
      cards.delete(id);
    }
    $("empty").hidden = cards.size > 0;
  }

  function status(s) {
    s.heard = ++heard;
    daemons.set(s.instance, s);
    renderDaemons();
  }

  const SHOWN_DAEMONS = 4;
  let heard = 0;

  function renderDaemons() {
    // live ones first, then the most recently heard: a flood of other statuses on the bus
    // cannot push a live daemon out of sight, and at most SHOWN_DAEMONS pills are drawn
    const live = (d) => d.state === "online" && !d.stale;
    const all = [...daemons.values()].sort((a, b) => live(b) - live(a) || b.heard - a.heard);
    const box = $("daemons");
    box.replaceChildren();
    for (const d of all.slice(0, SHOWN_DAEMONS)) {
      const state = d.stale ? "stale" : d.state;
      const pill = el("span", `pill ${state === "online" ? "ok" : state === "stale" ? "warn" : "bad"}`);
      pill.dataset.instance = d.instance;
      pill.dataset.state = state;
      if (d.stale) pill.title = "said online, but its reminders stopped: gone without a word";
      pill.append(
        el("strong", "", d.instance),
        // not its "streams": that is the count when it said so (over MQTT, when it started)
        document.createTextNode(` ${state} · started ${clock(d.started)} · mocapd ${d.version}`),
      );
      box.append(pill);
    }
    if (all.length > SHOWN_DAEMONS) {
      const rest = all.slice(SHOWN_DAEMONS);
      const more = el("span", "pill muted", `+${rest.length} more (${rest.filter(live).length} online)`);
      more.id = "daemons-more";
      more.title = rest.map((d) => `${d.instance}: ${d.stale ? "stale" : d.state}`).join("\n");
      box.append(more);
    }
    if (!daemons.size) box.append(el("span", "pill muted", "no daemon status yet"));
  }

  function health(h) {
    const pill = $("health");
    if (!h) {
      pill.className = "pill muted";
      pill.textContent = "health: not watched";
      return;
    }
    const state = h.healthy === null ? "no answer" : h.healthy ? "healthy" : `unhealthy: ${h.text}`;
    const drops = typeof h.drops === "number" ? ` · drops ${Math.round(h.drops)}` : "";
    pill.className = `pill ${h.healthy ? "ok" : "bad"}`;
    pill.textContent = `daemon ${state}${drops}`;
    pill.title = h.healthy === null ? h.text : "the daemon's /healthz and /metrics";
    pill.dataset.healthy = String(h.healthy);
    pill.dataset.drops = String(h.drops);
  }

  function bus(b) {
    const pill = $("bus");
    const dropped = b.dropped > 0 ? ` · ${b.dropped} dropped by the view` : "";
    pill.className = `pill ${!b.connected ? "bad" : b.dropped > 0 ? "warn" : "ok"}`;
    pill.textContent = `bus ${b.url} ${b.connected ? "connected" : b.problem} · ${b.received} messages · ${b.refused} refused${dropped}`;
    pill.title = b.dropped > 0 ? "the view's own queue overflowed: what it shows is thinned" : "";
    pill.dataset.dropped = String(b.dropped);
    pill.dataset.connected = String(b.connected);
  }

  function refused(r) {
    record.refused.push(r);
    if (record.refused.length > SHOWN_REFUSED) record.refused.shift();
    const li = el("li", "refusal");
    li.dataset.reason = r.reason;
    li.append(
      el("time", "muted small", clock(r.time)),
      el("span", "reason", r.reason),
      el("code", "topic", r.topic),
      el("span", "detail muted", r.detail),
    );
    const list = $("refused");
    list.prepend(li);
    while (list.childElementCount > SHOWN_REFUSED) list.lastChild.remove();
  }

  function snapshot(s) {
    // a snapshot comes on every (re)connect, and the server may have restarted and forgotten:
    // what the page has is merged, never wiped (cards it does not list are kept, ended)
    record.snapshots += 1;
    joints = s.joints;
    bones = s.bones;
    daemons.clear();
    for (const st of s.statuses) {
      st.heard = ++heard;
      daemons.set(st.instance, st);
    }
    renderDaemons();
    const listed = new Set();
    for (const info of s.streams) {
      if (info.ended && dismissed.has(info.stream)) continue;
      listed.add(info.stream);
      const c = card(info);
      if (info.pose) c.setPose(info.pose);
      if (info.progress) c.setProgress(info.progress);
      for (const d of info.detections) c.addDetection(d);
      c.setStats(info.stats);
    }
    for (const [id, c] of cards) if (!listed.has(id)) c.setEnded(true);
    for (const d of s.log) logDetection(d);
    $("refused").replaceChildren();
    record.refused = [];
    for (const r of s.refused) refused(r);
    $("refused-count").textContent = String(Object.values(s.refusals).reduce((a, b) => a + b, 0));
    bus(s.bus);
    health(s.health);
    $("empty").hidden = cards.size > 0;
  }

  // ------------------------------------------------------------------- the session's detections

  function logDetection(d) {
    if (sessionLog.has(d.id)) return;
    sessionLog.set(d.id, d);
    if (sessionLog.size > LOG_KEPT) sessionLog.delete(sessionLog.keys().next().value);
    if (!logStreams.has(d.stream)) {
      logStreams.add(d.stream);
      $("log-stream").append(el("option", "", d.stream));
    }
    scheduleLog();
  }

  function logged() {
    const stream = $("log-stream").value;
    const cls = $("log-class").value.trim().toLowerCase();
    return [...sessionLog.values()].filter(
      (d) => (!stream || d.stream === stream) && (!cls || d.class.toLowerCase().includes(cls)),
    );
  }

  let logPending = false;
  function scheduleLog() {
    if (logPending) return;
    logPending = true;
    requestAnimationFrame(() => {
      logPending = false;
      renderLog();
    });
  }

  function renderLog() {
    const rows = logged();
    $("log-count").textContent = String(sessionLog.size);
    const body = $("log-rows");
    body.replaceChildren();
    for (const d of rows.slice(-SHOWN_LOG).reverse()) {
      const tr = el("tr");
      tr.dataset.id = d.id;
      for (const text of [d.stream, d.class, `${d.start_frame}–${d.end_frame}`, fixed(d.cost, 3), clock(d.emit_time)]) {
        tr.append(el("td", "", text));
      }
      body.append(tr);
    }
    $("log-shown").textContent = rows.length > SHOWN_LOG ? `latest ${SHOWN_LOG} of ${rows.length}` : `${rows.length}`;
  }

  const LOG_FIELDS = ["stream", "class", "start_frame", "end_frame", "cost", "tau", "emitted_at_frame", "emit_time", "id"];

  function csvField(v) {
    const text = v === null || v === undefined ? "" : String(v);
    return /[",\n\r]/.test(text) ? `"${text.replace(/"/g, '""')}"` : text;
  }

  function download(name, type, text) {
    const url = URL.createObjectURL(new Blob([text], { type }));
    const a = el("a");
    a.href = url;
    a.download = name;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10_000);
  }

  function exportLog(kind) {
    const rows = logged();
    if (kind === "json") {
      const picked = rows.map((d) => Object.fromEntries(LOG_FIELDS.map((f) => [f, d[f] ?? null])));
      download("mocapd-detections.json", "application/json", JSON.stringify(picked, null, 1));
    } else {
      const lines = [LOG_FIELDS.join(","), ...rows.map((d) => LOG_FIELDS.map((f) => csvField(d[f])).join(","))];
      download("mocapd-detections.csv", "text/csv", lines.join("\n") + "\n");
    }
  }

  const handlers = {
    snapshot,
    stream: card,
    gone: (m) => gone(m.stream),
    poses: (m) => {
      for (const p of m.poses) cards.get(p.stream)?.setPose(p);
    },
    progress: (m) => cards.get(m.stream)?.setProgress(m),
    detection: (m) => {
      cards.get(m.stream)?.addDetection(m);
      logDetection(m);
    },
    ended: (m) => cards.get(m.stream)?.setEnded(true),
    status,
    status_gone: (m) => {
      daemons.delete(m.instance);
      renderDaemons();
    },
    refused: (m) => {
      refused(m);
      const n = $("refused-count");
      n.textContent = String(Number(n.textContent) + 1);
    },
    stats: (m) => {
      for (const s of m.streams) cards.get(s.stream)?.setStats(s);
    },
    bus: (m) => {
      bus(m);
      $("refused-count").textContent = String(m.refused);
    },
    health,
  };

  // --------------------------------------------------------------------------- the connection

  let retry = 500;
  function connect() {
    const link = $("link");
    const token = new URLSearchParams(location.search).get("token");
    const query = token ? `?token=${encodeURIComponent(token)}` : "";
    const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${query}`);
    ws.onopen = () => {
      retry = 500;
      record.connected = true;
      link.className = "pill ok";
      link.textContent = "live";
    };
    ws.onmessage = (e) => {
      record.messages += 1;
      const m = JSON.parse(e.data);
      const handle = Object.prototype.hasOwnProperty.call(handlers, m.type) ? handlers[m.type] : null;
      if (handle) handle(m);
    };
    ws.onclose = () => {
      record.connected = false;
      link.className = "pill bad";
      link.textContent = "disconnected: reconnecting…";
      setTimeout(connect, retry);
      retry = Math.min(5000, retry * 2);
    };
  }

  // ------------------------------------------------------------------------------- the drawing

  let second = performance.now();
  let inSecond = 0;
  function frame(now) {
    record.frames += 1;
    inSecond += 1;
    if (now - second >= 1000) {
      record.fps = (inSecond * 1000) / (now - second);
      $("fps").textContent = `${fixed(record.fps, 0)} fps`;
      second = now;
      inSecond = 0;
    }
    for (const c of cards.values()) c.draw(now);
    requestAnimationFrame(frame);
  }

  $("log-stream").addEventListener("change", renderLog);
  $("log-class").addEventListener("input", renderLog);
  $("log-csv").addEventListener("click", () => exportLog("csv"));
  $("log-json").addEventListener("click", () => exportLog("json"));
  connect();
  requestAnimationFrame(frame);
})();
