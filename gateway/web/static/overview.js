// Live overview: the server sends the changed rows once per cycle (server-sent events).
// Without JavaScript the page still shows the rows as of its loading.
"use strict";
(function () {
  function text(v, digits) {
    if (v === null || v === undefined) return "–";
    return typeof v === "number" ? v.toFixed(digits) : String(v);
  }
  function sensors(cell, list) {
    cell.textContent = "";
    list.forEach(function (s) {
      var span = document.createElement("span");
      span.className = "sensor " + s.quality;
      span.dataset.sensor = s.name;
      span.title = s.quality + (s.reason ? ": " + s.reason : "");
      span.textContent = s.name + " " + text(s.value_C, 1) + " °C";
      if (s.reason) {
        var em = document.createElement("em");
        em.textContent = s.reason;
        span.appendChild(em);
      }
      cell.appendChild(span);
    });
  }
  function health(cell, counters) {
    cell.textContent = "";
    Object.keys(counters || {}).forEach(function (k) {
      if (!counters[k]) return;
      cell.appendChild(document.createTextNode(k + " " + counters[k]));
      cell.appendChild(document.createElement("br"));
    });
  }
  function axes(cell, list) {
    // a multi-axis machine's axes: "Z predicted / applied", held ones marked
    if (!cell) return;
    cell.textContent = "";
    list.forEach(function (a) {
      var span = document.createElement("span");
      span.className = "axis" + (a.held ? " held" : "");
      span.dataset.axis = a.axis;
      span.title = a.axis + ": predicted / applied µm; write: " + a.write_status;
      span.textContent = a.axis + " " + text(a.predicted_um, 1) + " / " + text(a.applied_um, 1);
      cell.appendChild(span);
      cell.appendChild(document.createTextNode(" "));
    });
  }
  function update(row) {
    var tr = document.getElementById("row-" + row.machine);
    if (!tr) return;
    var set = function (f, v) { var c = tr.querySelector('[data-f="' + f + '"]'); if (c) c.textContent = v; };
    set("state", row.state);
    set("regime", text(row.regime));
    set("model_id", text(row.model_id) + " v" + row.models_version);
    set("predicted_um", text(row.predicted_um, 1));
    set("interval_um", text(row.interval_um, 1));
    var outside = row.outside_inputs || [];
    set("training_span", text(row.training_span) + (outside.length ? ": " + outside.join(", ") : ""));
    var span = tr.querySelector('[data-f="training_span"]');
    if (span) span.className = row.training_span === "outside" ? "flag" : "";
    set("applied_um", text(row.applied_um, 1));
    set("written_cnc", text(row.written_cnc, 4) + " " + row.cnc_unit);
    set("write_status", text(row.write_status));
    set("probe_residual_um", text(row.probe_residual_um, 1));
    sensors(tr.querySelector('[data-f="sensors"]'), row.sensors || []);
    health(tr.querySelector('[data-f="health"]'), row.health);
    axes(tr.querySelector('[data-f="axes"]'), row.axes || []);
    tr.dataset.updates = String(Number(tr.dataset.updates || 0) + 1);
  }
  var live = document.getElementById("live");
  var source = new EventSource("/events");
  source.addEventListener("rows", function (e) {
    JSON.parse(e.data).forEach(update);
    live.textContent = "live, " + new Date().toLocaleTimeString();
  });
  source.onerror = function () { live.textContent = "connection lost, retrying"; };
})();
