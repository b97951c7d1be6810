// esc-bridge monitor's page: hand-written, part of esc-bridge (MIT licence).
//
// It renders what the monitor sends on /events and judges nothing itself: the monitor says
// each card's and row's level, the cells' texts and each chart point (bridge/monitor/web/
// model.py). Two events: "hello" (the columns and the last minute of chart points, on every
// connection) and "snapshot" (every vehicle, several times a second). Text from the network
// only ever goes in as textContent.
"use strict";

(function () {
  const PALETTE = [
    "#2563eb", "#dc2626", "#16a34a", "#d97706",
    "#7c3aed", "#0891b2", "#db2777", "#65a30d",
  ];
  // [series, title, whether the axis starts at zero]: temperatures sit far above it.
  const CHARTS = [
    ["rpm", "rpm", true],
    ["current_a", "current, A", true],
    ["temp_c", "temperature, °C (hottest sensor)", false],
  ];

  const page = {
    columns: [],
    windowS: 60,
    series: ["rpm", "current_a", "temp_c"],
    cards: new Map(),
    history: {},
    t: 0,
    drawQueued: false,
  };

  function element(tag, className, text) {
    const node = document.createElement(tag);
    if (className) node.className = className;
    if (text !== undefined) node.textContent = text;
    return node;
  }

  function setText(node, text) {
    if (node.textContent !== text) node.textContent = text;
  }

  function setClass(node, className) {
    if (node.className !== className) node.className = className;
  }

  // -- the connection -----------------------------------------------------------------------

  function connect() {
    const events = new EventSource("events");
    const connection = document.getElementById("connection");
    events.addEventListener("open", function () {
      setText(connection, "live");
      setClass(connection, "connection up");
    });
    events.addEventListener("error", function () {
      // EventSource reconnects by itself; until then the values shown are the last known.
      setText(connection, "disconnected: retrying");
      setClass(connection, "connection down");
    });
    events.addEventListener("hello", function (event) {
      onHello(JSON.parse(event.data));
    });
    events.addEventListener("snapshot", function (event) {
      onSnapshot(JSON.parse(event.data));
    });
  }

  function onHello(hello) {
    page.columns = hello.columns;
    page.windowS = hello.window_s;
    page.series = hello.series;
    page.history = hello.history;
    setText(document.getElementById("source"), "watching " + hello.source);
    // On every (re)connection the monitor's history replaces what this page had gathered.
    page.cards.forEach(function (card, name) {
      card.buffer = page.history[name] ? bufferFrom(page.history[name]) : emptyBuffer();
      buildHeader(card);
    });
  }

  function onSnapshot(snapshot) {
    page.t = snapshot.t;
    const waiting = document.getElementById("waiting");
    if (waiting) waiting.hidden = snapshot.vehicles.length > 0;
    for (const vehicle of snapshot.vehicles) {
      let card = page.cards.get(vehicle.name);
      if (!card) card = addCard(vehicle.name);
      updateCard(card, vehicle);
      if (vehicle.point) addPoint(card.buffer, snapshot.t, vehicle.point);
      trim(card.buffer, snapshot.t - page.windowS);
    }
    if (!page.drawQueued) {
      page.drawQueued = true;
      requestAnimationFrame(drawAll);
    }
  }

  // -- a vehicle's card ---------------------------------------------------------------------

  function addCard(name) {
    const section = element("section", "vehicle");
    section.dataset.vehicle = name;
    const head = element("div", "head");
    head.append(element("h2", "", name));
    const summary = element("span", "summary");
    head.append(summary);
    const alerts = element("ul", "alerts");
    const health = element("dl", "health");
    const wrap = element("div", "table-wrap");
    const table = element("table");
    const thead = element("thead");
    const tbody = element("tbody");
    table.append(thead, tbody);
    wrap.append(table);
    const charts = element("div", "charts");
    const canvases = {};
    for (const [series, title] of CHARTS) {
      const figure = element("figure");
      figure.dataset.chart = series;
      figure.append(element("figcaption", "", title + ", last minute"));
      const canvas = element("canvas");
      figure.append(canvas);
      charts.append(figure);
      canvases[series] = canvas;
    }
    const legend = element("div", "legend");
    const note = element("p", "note");
    section.append(head, alerts, health, wrap, charts, legend, note);

    const card = {
      section, summary, alerts, health, thead, tbody, legend, note, canvases,
      rows: new Map(),
      motors: 0,
      buffer: emptyBuffer(),
    };
    const history = page.history[name];
    if (history) card.buffer = bufferFrom(history);
    buildHeader(card);
    page.cards.set(name, card);
    insertSorted(section, name);
    return card;
  }

  function insertSorted(section, name) {
    const main = document.getElementById("vehicles");
    const after = Array.from(main.querySelectorAll("section.vehicle")).find(function (other) {
      return other.dataset.vehicle > name;
    });
    main.insertBefore(section, after || null);
  }

  function buildHeader(card) {
    const row = element("tr");
    for (const column of page.columns) {
      const th = element("th", columnClass(column), column.name);
      row.append(th);
    }
    card.thead.replaceChildren(row);
    card.tbody.replaceChildren();
    card.rows.clear();
  }

  function columnClass(column) {
    return column.align + (column.minor ? " minor" : "");
  }

  function updateCard(card, vehicle) {
    setClass(card.section, "vehicle level-" + vehicle.level);
    setText(card.summary, vehicle.summary);
    card.section.dataset.stale = vehicle.stale ? "true" : "false";

    syncList(card.alerts, vehicle.alerts, function (li, text) {
      setText(li, text);
    }, "li");
    syncList(card.health, vehicle.health, function (div, item) {
      if (!div.firstChild) div.append(element("dt"), element("dd"));
      setClass(div, "level-" + item.level);
      div.dataset.item = item.name;
      setText(div.firstChild, item.name);
      setText(div.lastChild, item.text);
    }, "div");

    const seen = new Set();
    for (const esc of vehicle.escs) {
      seen.add(esc.motor);
      let row = card.rows.get(esc.motor);
      if (!row) row = addRow(card, esc.motor);
      setClass(row, "esc-" + esc.level);
      esc.cells.forEach(function (text, index) {
        if (row.cells[index]) setText(row.cells[index], text);
      });
    }
    card.rows.forEach(function (row, motor) {
      if (!seen.has(motor)) {
        row.remove();
        card.rows.delete(motor);
      }
    });
    if (vehicle.escs.length !== card.motors) {
      card.motors = vehicle.escs.length;
      buildLegend(card);
    }
    setText(card.note, vehicle.note || "");
  }

  function syncList(parent, items, fill, tag) {
    while (parent.children.length > items.length) parent.lastChild.remove();
    while (parent.children.length < items.length) parent.append(element(tag));
    items.forEach(function (item, index) {
      fill(parent.children[index], item);
    });
  }

  function addRow(card, motor) {
    const row = element("tr");
    row.dataset.motor = String(motor);
    for (const column of page.columns) {
      const td = element("td", columnClass(column));
      td.dataset.col = column.name;
      row.append(td);
    }
    const after = Array.from(card.rows.keys()).filter(function (m) { return m > motor; });
    const next = after.length ? card.rows.get(Math.min.apply(null, after)) : null;
    card.tbody.insertBefore(row, next);
    card.rows.set(motor, row);
    return row;
  }

  function buildLegend(card) {
    const spans = [];
    for (let m = 0; m < card.motors; m++) {
      const span = element("span", "", "motor " + (m + 1));
      span.style.setProperty("--swatch", PALETTE[m % PALETTE.length]);
      spans.push(span);
    }
    card.legend.replaceChildren.apply(card.legend, spans);
  }

  // -- chart buffers: {t: [...], <series>: [per motor: [...]]} ------------------------------

  function emptyBuffer() {
    const buffer = { t: [] };
    for (const series of page.series) buffer[series] = [];
    return buffer;
  }

  function bufferFrom(history) {
    const buffer = { t: history.t.slice() };
    for (const series of page.series) {
      buffer[series] = (history[series] || []).map(function (values) { return values.slice(); });
    }
    return buffer;
  }

  function addPoint(buffer, t, point) {
    const index = buffer.t.length;
    buffer.t.push(t);
    page.series.forEach(function (series, s) {
      const lines = buffer[series];
      while (lines.length < point.length) lines.push(new Array(index).fill(null));
      lines.forEach(function (line, m) {
        line.push(m < point.length ? point[m][s] : null);
      });
    });
  }

  function trim(buffer, oldest) {
    let drop = 0;
    while (drop < buffer.t.length && buffer.t[drop] < oldest) drop++;
    if (!drop) return;
    buffer.t.splice(0, drop);
    for (const series of page.series) {
      for (const line of buffer[series]) line.splice(0, drop);
    }
  }

  // -- drawing ------------------------------------------------------------------------------

  function drawAll() {
    page.drawQueued = false;
    const style = getComputedStyle(document.documentElement);
    const colours = {
      line: style.getPropertyValue("--line").trim(),
      dim: style.getPropertyValue("--dim").trim(),
    };
    page.cards.forEach(function (card) {
      for (const [series, , fromZero] of CHARTS) {
        draw(card.canvases[series], card.buffer.t, card.buffer[series] || [], fromZero, colours);
      }
    });
  }

  function draw(canvas, times, lines, fromZero, colours) {
    const ratio = window.devicePixelRatio || 1;
    const width = canvas.clientWidth;
    const height = canvas.clientHeight;
    if (!width || !height) return;
    if (canvas.width !== Math.round(width * ratio)) canvas.width = Math.round(width * ratio);
    if (canvas.height !== Math.round(height * ratio)) canvas.height = Math.round(height * ratio);
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, width, height);

    let low = fromZero ? 0 : Infinity;
    let high = fromZero ? 0 : -Infinity;
    for (const line of lines) {
      for (const value of line) {
        if (value === null) continue;
        if (value < low) low = value;
        if (value > high) high = value;
      }
    }
    if (low === Infinity) {
      low = 0;
      high = 1;
    }
    if (high === low) high = low + 1;
    const span = niceStep((high - low) / 3);
    low = Math.floor(low / span) * span;
    high = Math.ceil(high / span) * span;

    const left = 40;
    const right = width - 4;
    const top = 8;
    const bottom = height - 14;
    const x = function (t) { return right - (page.t - t) / page.windowS * (right - left); };
    const y = function (v) { return bottom - (v - low) / (high - low) * (bottom - top); };

    ctx.font = "10px system-ui, sans-serif";
    ctx.fillStyle = colours.dim;
    ctx.strokeStyle = colours.line;
    ctx.lineWidth = 1;
    ctx.textAlign = "right";
    ctx.textBaseline = "middle";
    for (let v = low; v <= high + span / 2; v += span) {
      ctx.beginPath();
      ctx.moveTo(left, Math.round(y(v)) + 0.5);
      ctx.lineTo(right, Math.round(y(v)) + 0.5);
      ctx.stroke();
      ctx.fillText(label(v), left - 4, y(v));
    }
    ctx.textBaseline = "alphabetic";
    ctx.textAlign = "left";
    ctx.fillText("-" + page.windowS + " s", left, height - 2);
    ctx.textAlign = "right";
    ctx.fillText("now", right, height - 2);

    ctx.save();
    ctx.beginPath();
    ctx.rect(left, 0, right - left, height);
    ctx.clip();
    ctx.lineWidth = 1.5;
    lines.forEach(function (line, m) {
      ctx.strokeStyle = PALETTE[m % PALETTE.length];
      ctx.beginPath();
      let drawing = false;
      line.forEach(function (value, i) {
        if (value === null) {
          drawing = false;
          return;
        }
        if (drawing) ctx.lineTo(x(times[i]), y(value));
        else ctx.moveTo(x(times[i]), y(value));
        drawing = true;
      });
      ctx.stroke();
    });
    ctx.restore();
  }

  function niceStep(rough) {
    const power = Math.pow(10, Math.floor(Math.log10(rough)));
    for (const factor of [1, 2, 5, 10]) {
      if (factor * power >= rough) return factor * power;
    }
    return 10 * power;
  }

  function label(value) {
    const magnitude = Math.abs(value);
    if (magnitude >= 10000) return (value / 1000).toFixed(0) + "k";
    if (magnitude >= 1000) return (value / 1000).toFixed(1) + "k";
    return String(Math.round(value * 10) / 10);
  }

  connect();
})();
