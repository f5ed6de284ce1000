// bradyscope pages: upload progress bar and live job status. Plain JavaScript, no library.
// Pages work without it: forms post normally and the job page refreshes itself.
"use strict";

(function () {
  /**
   * The sentence of an error answer's ``detail``: our own errors give a sentence; FastAPI's
   * validation errors (422) a list of {loc, msg}, shown as "field: message" each. Null when
   * there is nothing to show (the caller then says what failed with the status).
   */
  function errorText(detail) {
    if (typeof detail === "string") return detail;
    if (!Array.isArray(detail)) return null;
    var parts = detail.map(function (item) {
      if (typeof item === "string") return item;
      if (!item || typeof item.msg !== "string") return null;
      var loc = Array.isArray(item.loc) ? item.loc.filter(function (p) {
        return ["body", "query", "path", "header", "cookie"].indexOf(p) < 0;
      }) : [];
      return (loc.length ? loc.join(" ") + ": " : "") + item.msg;
    }).filter(function (text) { return text; });
    if (!parts.length) return null;
    var text = parts.join("; ");
    return /[.!?]$/.test(text) ? text : text + ".";
  }
  window.BradyscopeApp = { errorText: errorText };

  function setupUpload(form) {
    var block = form.querySelector("[data-progress]");
    var bar = block ? block.querySelector("progress") : null;
    var text = form.querySelector("[data-progress-text]");
    var errorBox = form.querySelector("[data-error]");
    var button = form.querySelector("button[type=submit]");
    form.addEventListener("submit", function (event) {
      if (!window.FormData || !window.XMLHttpRequest) return; // plain form post
      event.preventDefault();
      var data = new FormData(form);
      var token = data.get("csrf_token");
      var xhr = new XMLHttpRequest();
      xhr.open("POST", form.action);
      xhr.setRequestHeader("Accept", "application/json");
      if (token) xhr.setRequestHeader("X-CSRF-Token", token);
      if (errorBox) { errorBox.hidden = true; errorBox.textContent = ""; }
      if (block) block.hidden = false;
      if (button) button.disabled = true;
      xhr.upload.addEventListener("progress", function (e) {
        if (!e.lengthComputable || !bar) return;
        var pct = Math.round((100 * e.loaded) / e.total);
        bar.value = pct;
        bar.textContent = pct + " %";
        if (text) text.textContent = pct + " % sent (" + (e.loaded / 1e6).toFixed(1) + " of " + (e.total / 1e6).toFixed(1) + " MB)";
      });
      xhr.upload.addEventListener("load", function () {
        if (text) text.textContent = "Sent. Checking the videos…";
        if (bar) bar.value = 100;
      });
      xhr.addEventListener("load", function () {
        var body = null;
        try { body = JSON.parse(xhr.responseText); } catch (err) { body = null; }
        if (xhr.status >= 200 && xhr.status < 300 && body && body.job_url) {
          if (text) text.textContent = "Accepted. Opening the progress page…";
          window.location.assign(body.job_url);
          return;
        }
        if (xhr.status === 401) { window.location.assign("/login?next=" + encodeURIComponent(window.location.pathname)); return; }
        showError((body && errorText(body.detail)) || "The upload failed (status " + xhr.status + "). Please retry.");
      });
      xhr.addEventListener("error", function () { showError("The connection was lost during the upload. Please retry."); });
      xhr.addEventListener("abort", function () { showError("The upload was cancelled."); });
      xhr.send(data);
    });
    function showError(message) {
      if (button) button.disabled = false;
      if (block) block.hidden = true;
      if (errorBox) {
        errorBox.textContent = message;
        errorBox.hidden = false;
        // a paragraph takes the focus only with a tabindex: else it stayed on <body>
        if (!errorBox.hasAttribute("tabindex")) errorBox.setAttribute("tabindex", "-1");
        errorBox.focus();
      }
    }
  }

  function setupJob(section) {
    var url = section.getAttribute("data-job-status-url");
    var statusEl = section.querySelector("[data-job-status]");
    var stageEl = section.querySelector("[data-job-stage]");
    var bar = section.querySelector("[data-job-progress]");
    var percent = section.querySelector("[data-job-percent]");
    var errorBox = section.querySelector("[data-job-error]");
    var errorText = section.querySelector("[data-job-error-text]");
    var done = section.querySelector("[data-job-done]");
    var delay = 1000;
    function update(job) {
      var pct = Math.round(100 * (job.progress || 0));
      if (job.status === "succeeded") pct = 100;
      statusEl.textContent = job.status;
      statusEl.className = "status status-" + job.status;
      stageEl.textContent = job.stage_label || job.stage || "";
      bar.value = pct; bar.textContent = pct + " %";
      percent.textContent = pct + " %";
      if (job.error) { errorText.textContent = job.error; errorBox.hidden = false; }
      if (job.status === "succeeded") {
        done.hidden = false;
        var link = done.querySelector("a");
        if (link) link.focus();
      }
      if (job.title) document.title = job.title + " — bradyscope";
      section.setAttribute("data-status", job.status);
    }
    function poll() {
      fetch(url, { headers: { Accept: "application/json" }, credentials: "same-origin", cache: "no-store" })
        .then(function (r) {
          if (r.status === 401) { window.location.assign("/login?next=" + encodeURIComponent(window.location.pathname)); return null; }
          return r.ok ? r.json() : null;
        })
        .then(function (job) {
          if (!job) { setTimeout(poll, 4000); return; }
          update(job);
          if (job.status === "queued" || job.status === "running") setTimeout(poll, delay);
        })
        .catch(function () { setTimeout(poll, 4000); });
    }
    var initial = section.getAttribute("data-status");
    if (initial === "queued" || initial === "running") setTimeout(poll, 300);
  }

  document.addEventListener("DOMContentLoaded", function () {
    Array.prototype.forEach.call(document.querySelectorAll("form[data-upload]"), setupUpload);
    var job = document.querySelector("[data-job-status-url]");
    if (job) setupJob(job);
  });
})();
