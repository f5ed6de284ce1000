// bradyscope capture station: two cameras, a live quality gate, recording, upload.
// Plain JavaScript, no library; the image analysis and the timestamps are in
// capture_gate.js. docs/capture.md tells what each step does and why.
"use strict";

(function () {
  var C = window.BradyscopeCapture;
  var SIDES = ["left", "right"];
  var GATE_PERIOD_MS = 250; // the gate looks at each camera 4 times a second
  var ANALYSED_WIDTH = 640; // px: larger frames are scaled down for the gate
  var FPS_WINDOW_MS = 2000;
  var MIN_FPS = 20; // Hz: below this the recording is refused as too slow
  var ADVISED_FPS = 50; // Hz: below this the gate advises a faster camera mode
  var MAX_WHITE = 0.02; // share of white pixels above which the picture is over-exposed
  var MAX_LOST = 5; // frames lost in the last seconds before the gate objects
  var UNSEEN_LIVE_S = 1; // s without every marker in a view before the recording's gate says so
  var UNSEEN_TAKE_S = 1; // s, and
  var UNSEEN_TAKE_SHARE = 0.1; // share of the take, without every marker: the quick check says so
  var SWAP_FIT_PX = 2.5; // px: the views fit the rig's geometry this well ...
  var SWAP_MISFIT_PX = 6; // px: ... and miss it by this much (and 3 times as much) the other way
  var SWAP_LOOKS = 12; // the looks at both views the cameras' order is judged on ...
  var SWAP_AGREE = 5; // ... of which this many, and none the other way, must say "swapped"
  var MIME_TYPES = [
    "video/webm;codecs=vp9",
    "video/webm;codecs=vp8",
    "video/webm",
    "video/mp4;codecs=avc1.640028",
    "video/mp4",
  ];

  function $(root, selector) { return root.querySelector(selector); }
  function sizeText(size) { return size ? size.w + " × " + size.h : ""; }
  function parseSize(text) {
    var m = /^(\d+)x(\d+)$/.exec(text || "");
    return m ? { w: Number(m[1]), h: Number(m[2]) } : null;
  }
  function sideName(side) { return side === "left" ? "left" : "right"; }
  function capital(text) { return text.charAt(0).toUpperCase() + text.slice(1); }

  function Station(root) {
    this.root = root;
    this.mode = root.getAttribute("data-mode");
    this.rigId = root.getAttribute("data-rig-id");
    this.trialRigId = root.getAttribute("data-trial-rig-id"); // "" = the session's rig
    this.uploadUrl = root.getAttribute("data-upload-url");
    this.csrf = root.getAttribute("data-csrf");
    this.markersExpected = Number(root.getAttribute("data-markers") || 0);
    try { // the rig's calibration, to tell swapped cameras ("" in calibration mode, or none yet)
      this.geometry = JSON.parse(root.getAttribute("data-geometry") || "null");
    } catch (e) {
      this.geometry = null;
    }
    this.orderLog = []; // what each look at both views said of the cameras' order
    this.swapped = null;
    this.lookTurn = 0;
    this.countdownS = Number(root.getAttribute("data-countdown-s") || 3);
    this.holeS = Number(root.getAttribute("data-hole-s") || 0.5); // the server's rule (core.video)
    this.holeFrames = Number(root.getAttribute("data-hole-frames") || 10);
    this.needed = {
      left: parseSize(root.getAttribute("data-left-size")),
      right: parseSize(root.getAttribute("data-right-size")),
    };
    this.form = $(root, "[data-capture-form]");
    this.taskSelect = $(root, "[data-task-select]");
    this.limbText = $(root, "[data-limb-text]");
    this.sizeSelect = $(root, "[data-size-select]");
    this.lockBox = $(root, "[data-lock-exposure]");
    this.exposureHint = $(root, "[data-exposure-hint]");
    this.errorBox = $(root, "[data-capture-error]");
    this.errorText = $(root, "[data-capture-error-text]");
    this.retryButton = $(root, "[data-retry-access]");
    this.gateBox = $(root, "[data-gate]");
    this.startButton = $(root, "[data-start]");
    this.stopButton = $(root, "[data-stop]");
    this.countdownBox = $(root, "[data-countdown]");
    this.timerBox = $(root, "[data-timer]");
    this.uploadBlock = $(root, "[data-upload-block]");
    this.uploadBar = $(root, "[data-upload-progress]");
    this.uploadText = $(root, "[data-upload-text]");
    this.takeBox = $(root, "[data-take]");
    this.afterBox = $(root, "[data-after]");
    this.uploadAgainButton = $(root, "[data-upload-again]");
    this.retakeButton = $(root, "[data-retake]");
    this.phase = "setup"; // setup, countdown, recording, finishing, uploading, done
    this.devices = [];
    this.listed = false; // the cameras were listed at least once
    this.noCamera = false; // the browser found no camera at all
    this.take = null;
    this.cams = {};
    var self = this;
    SIDES.forEach(function (side) {
      var view = $(root, '[data-view="' + side + '"]');
      self.cams[side] = {
        side: side,
        select: $(root, '[data-camera="' + side + '"]'),
        view: view,
        video: $(view, "[data-video]"),
        state: $(view, "[data-view-state]"),
        stream: null,
        track: null,
        deviceId: "",
        opening: 0,
        size: null,
        problem: null, // why this camera cannot record (hard)
        notes: [], // what the gate objects to (soft)
        frames: [], // recent {media_s, at_ms} seen by requestVideoFrameCallback
        log: null, // capture times (s) while recording
        statsLog: [],
        gate: null,
      };
    });
    this.canvas = document.createElement("canvas");
    this.ctx = this.canvas.getContext("2d", { willReadFrequently: true });
  }

  // -- messages -------------------------------------------------------------------------

  Station.prototype.showError = function (message, retry) {
    this.errorText.textContent = message;
    this.retryButton.hidden = !retry;
    this.errorBox.hidden = false;
    this.errorBox.focus();
  };

  Station.prototype.clearError = function () {
    this.errorBox.hidden = true;
    this.errorText.textContent = "";
  };

  function accessMessage(error) {
    var name = error && error.name;
    if (name === "NotAllowedError" || name === "SecurityError") {
      return "The browser was not allowed to use the cameras. Allow camera access for this site"
        + " (the camera symbol in the address bar, or the browser's site settings), then press"
        + " “Retry camera access”.";
    }
    if (name === "NotFoundError" || name === "OverconstrainedError") {
      return "No camera was found. Connect the two cameras, then press “Retry camera access”.";
    }
    if (name === "NotReadableError" || name === "AbortError") {
      return "A camera could not be started: another program may be using it. Close that"
        + " program, then press “Retry camera access”.";
    }
    return "The cameras could not be started (" + (error && error.message ? error.message : name)
      + "). Reconnect them, then press “Retry camera access”.";
  }

  // -- cameras --------------------------------------------------------------------------

  Station.prototype.start = function () {
    var self = this;
    var md = navigator.mediaDevices;
    if (!md || !md.getUserMedia || !window.MediaRecorder) {
      this.showError("This browser cannot record from cameras on this page. Use a current"
        + " Chromium, Chrome, Edge or Firefox, and open the site over https (or as localhost).", false);
      return;
    }
    SIDES.forEach(function (side) {
      self.cams[side].select.addEventListener("change", function () { self.choose(side); });
    });
    if (this.sizeSelect) {
      this.sizeSelect.addEventListener("change", function () {
        SIDES.forEach(function (side) { if (self.cams[side].deviceId) self.open(side, self.cams[side].deviceId); });
      });
    }
    if (this.taskSelect) {
      this.taskSelect.addEventListener("change", function () { self.chooseTask(); });
      this.chooseTask();
    }
    this.lockBox.addEventListener("change", function () { self.lockExposure(self.lockBox.checked); });
    this.retryButton.addEventListener("click", function () { self.requestAccess(); });
    this.startButton.addEventListener("click", function () { self.countdown(); });
    this.stopButton.addEventListener("click", function () { self.stopRecording(); });
    this.retakeButton.addEventListener("click", function () { self.retake(); });
    this.uploadAgainButton.addEventListener("click", function () { self.upload(); });
    md.addEventListener("devicechange", function () { self.listDevices(); });
    document.addEventListener("visibilitychange", function () { self.pageHidden(); });
    window.setInterval(function () { self.tick(); }, GATE_PERIOD_MS);
    this.requestAccess();
  };

  Station.prototype.requestAccess = function () {
    var self = this;
    this.clearError();
    return navigator.mediaDevices.getUserMedia({ video: true })
      .then(function (stream) {
        stream.getTracks().forEach(function (t) { t.stop(); });
        self.noCamera = false;
        return self.listDevices(true);
      })
      .catch(function (error) {
        self.noCamera = error && (error.name === "NotFoundError" || error.name === "OverconstrainedError");
        self.showError(accessMessage(error), true);
        self.updateGate();
      });
  };

  Station.prototype.remembered = function () {
    try {
      return JSON.parse(window.localStorage.getItem("bradyscope.capture.rig-" + this.rigId) || "{}");
    } catch (e) {
      return {};
    }
  };

  Station.prototype.remember = function () {
    var choice = {};
    var self = this;
    SIDES.forEach(function (side) {
      var cam = self.cams[side];
      var device = self.devices.filter(function (d) { return d.deviceId === cam.deviceId; })[0];
      if (device) choice[side] = { id: device.deviceId, label: device.label };
    });
    try {
      window.localStorage.setItem("bradyscope.capture.rig-" + this.rigId, JSON.stringify(choice));
    } catch (e) { /* private browsing: the choice is not remembered */ }
  };

  Station.prototype.listDevices = function (restore) {
    var self = this;
    return navigator.mediaDevices.enumerateDevices().then(function (all) {
      self.devices = all.filter(function (d) { return d.kind === "videoinput" && d.deviceId; });
      self.listed = true;
      if (!self.devices.length) {
        self.showError("No camera was found. Connect the two cameras, then press “Retry camera access”.", true);
      }
      var saved = restore ? self.remembered() : {};
      SIDES.forEach(function (side) {
        var select = self.cams[side].select, keep = select.value;
        while (select.options.length > 1) select.remove(1);
        self.devices.forEach(function (d, i) {
          var option = document.createElement("option");
          option.value = d.deviceId;
          option.textContent = d.label || "Camera " + (i + 1);
          select.appendChild(option);
        });
        var wanted = saved[side];
        var match = wanted && self.devices.filter(function (d) {
          return d.deviceId === wanted.id;
        })[0];
        if (!match && wanted && wanted.label) {
          match = self.devices.filter(function (d) { return d.label === wanted.label; })[0];
        }
        select.value = match ? match.deviceId : keep;
        if (select.value !== keep || (match && !self.cams[side].stream)) self.choose(side);
      });
      self.updateGate();
    });
  };

  Station.prototype.choose = function (side) {
    var cam = this.cams[side];
    var other = this.cams[side === "left" ? "right" : "left"];
    var id = cam.select.value;
    if (!id) {
      this.close(side);
      cam.state.textContent = "No camera chosen.";
      this.updateGate();
      return;
    }
    if (id === other.select.value) {
      this.close(side);
      cam.deviceId = id;
      cam.problem = "The same camera is chosen for the left and the right side; choose two"
        + " different cameras.";
      cam.state.textContent = cam.problem;
      this.updateGate();
      return;
    }
    if (other.problem && other.select.value && other.deviceId === other.select.value && !other.stream) {
      this.open(other.side, other.select.value); // it was refused as a duplicate of this one
    }
    this.open(side, id);
  };

  /** The task decides how many markers the gate expects in each view (0: not counted). */
  Station.prototype.chooseTask = function () {
    var option = this.taskSelect.options[this.taskSelect.selectedIndex];
    if (!option) return;
    this.markersExpected = Number(option.getAttribute("data-markers") || 0);
    if (this.limbText) this.limbText.textContent = option.getAttribute("data-limb") || "hand";
    // The links to the clinic's other rigs keep the task chosen (?rig=...&task=...).
    Array.prototype.forEach.call(this.root.querySelectorAll("a[data-other-rig]"), function (a) {
      a.href = a.href.replace(/([?&]task=)[^&#]*/, "$1" + encodeURIComponent(option.value));
    });
    var self = this;
    SIDES.forEach(function (side) { if (self.cams[side].gate) self.showFacts(self.cams[side]); });
    if (this.phase === "setup") this.updateGate();
  };

  Station.prototype.neededSize = function (side) {
    if (this.mode === "calibration") return this.sizeSelect ? parseSize(this.sizeSelect.value) : null;
    return this.needed[side];
  };

  Station.prototype.close = function (side) {
    var cam = this.cams[side];
    cam.opening += 1;
    if (cam.stream) cam.stream.getTracks().forEach(function (t) { t.stop(); });
    cam.stream = null;
    cam.track = null;
    cam.video.srcObject = null;
    cam.size = null;
    cam.problem = null;
    cam.notes = [];
    cam.frames = [];
    cam.statsLog = [];
    cam.gate = null;
    cam.deviceId = "";
    this.orderLog = []; // judged again on the new pair of cameras
    this.swapped = null;
  };

  Station.prototype.open = function (side, deviceId) {
    var self = this;
    var cam = this.cams[side];
    this.close(side);
    var ticket = cam.opening;
    cam.deviceId = deviceId;
    cam.state.textContent = "Starting the camera…";
    var need = this.neededSize(side);
    var video = { deviceId: { exact: deviceId }, frameRate: { ideal: 240 }, resizeMode: "none" };
    if (need) { video.width = { ideal: need.w }; video.height = { ideal: need.h }; }
    return navigator.mediaDevices.getUserMedia({ video: video })
      .then(function (stream) {
        if (ticket !== cam.opening) { stream.getTracks().forEach(function (t) { t.stop(); }); return null; }
        cam.stream = stream;
        cam.track = stream.getVideoTracks()[0];
        cam.track.addEventListener("ended", function () { self.cameraLost(side); });
        return self.fastest(cam, video).then(function () {
          cam.video.srcObject = stream;
          var playing = cam.video.play();
          return playing && playing.catch ? playing.catch(function () { return null; }) : null;
        }).then(function () { return self.whenSized(cam); });
      })
      .then(function () {
        if (ticket !== cam.opening || !cam.track) return;
        self.watchFrames(cam);
        self.checkSize(cam);
        self.offerExposureLock();
        self.remember();
        self.updateGate();
      })
      .catch(function (error) {
        if (ticket !== cam.opening) return;
        cam.problem = capital(sideName(side)) + " camera: " + accessMessage(error);
        cam.state.textContent = cam.problem;
        self.updateGate();
      });
  };

  /** Ask for the highest frame rate the camera offers (at the needed size). */
  Station.prototype.fastest = function (cam, video) {
    var caps = cam.track.getCapabilities ? cam.track.getCapabilities() : {};
    var max = caps.frameRate && caps.frameRate.max;
    if (!max) return Promise.resolve();
    var wanted = Object.assign({}, video, { frameRate: { ideal: max } });
    delete wanted.deviceId;
    return cam.track.applyConstraints(wanted).catch(function () { return null; });
  };

  Station.prototype.whenSized = function (cam) {
    if (cam.video.videoWidth) return Promise.resolve();
    return new Promise(function (resolve) {
      var done = function () { cam.video.removeEventListener("loadedmetadata", done); resolve(); };
      cam.video.addEventListener("loadedmetadata", done);
      window.setTimeout(done, 3000);
    });
  };

  Station.prototype.checkSize = function (cam) {
    var settings = cam.track.getSettings ? cam.track.getSettings() : {};
    var w = cam.video.videoWidth || settings.width, h = cam.video.videoHeight || settings.height;
    cam.size = w && h ? { w: w, h: h } : null;
    var need = this.neededSize(cam.side);
    $(cam.view, '[data-fact="size"]').textContent = cam.size ? sizeText(cam.size) + " px" : "–";
    if (need && cam.size && (cam.size.w !== need.w || cam.size.h !== need.h)) {
      cam.problem = "The " + cam.side + " camera delivers " + sizeText(cam.size) + " px, but "
        + (this.mode === "calibration"
          ? "the chosen resolution is " + sizeText(need) + " px: choose a resolution this camera offers."
          : "the rig was calibrated at " + sizeText(need) + " px: set the camera to "
            + sizeText(need) + " px (or choose the camera the rig was calibrated with), or calibrate"
            + " the rig at " + sizeText(cam.size) + " px.");
      cam.state.textContent = cam.problem;
    } else {
      cam.problem = null;
      cam.state.textContent = "Camera running.";
    }
  };

  Station.prototype.offerExposureLock = function () {
    var self = this;
    var running = SIDES.map(function (s) { return self.cams[s]; }).filter(function (c) { return c.track; });
    var lockable = running.length > 0 && running.every(function (c) {
      var caps = c.track.getCapabilities ? c.track.getCapabilities() : {};
      return caps.exposureMode && caps.exposureMode.indexOf("manual") >= 0;
    });
    this.lockBox.disabled = !lockable;
    this.exposureHint.textContent = !running.length
      ? "Choose the cameras first."
      : lockable
        ? "Locks the exposure the cameras use now; set the light first."
        : "This browser cannot lock these cameras' exposure; set a short, fixed exposure in the camera's own settings (about 4 ms or less, so the fingertips do not blur; set the light first).";
  };

  Station.prototype.lockExposure = function (lock) {
    var self = this;
    SIDES.forEach(function (side) {
      var cam = self.cams[side];
      if (!cam.track) return;
      cam.track.applyConstraints({ advanced: [{ exposureMode: lock ? "manual" : "continuous" }] })
        .catch(function () {
          self.lockBox.checked = false;
          self.exposureHint.textContent = "The " + side + " camera refused to lock its exposure.";
        });
    });
  };

  Station.prototype.watchFrames = function (cam) {
    var video = cam.video;
    if (!video.requestVideoFrameCallback) return; // the gate then measures with track.stats only
    var stream = cam.stream;
    var onFrame = function (now, meta) {
      if (cam.stream !== stream) return;
      var media = typeof meta.mediaTime === "number" ? meta.mediaTime : now / 1000;
      cam.frames.push({ media_s: media, at_ms: now });
      while (cam.frames.length && now - cam.frames[0].at_ms > FPS_WINDOW_MS) cam.frames.shift();
      if (cam.log) cam.log.push(media);
      video.requestVideoFrameCallback(onFrame);
    };
    video.requestVideoFrameCallback(onFrame);
  };

  Station.prototype.cameraLost = function (side) {
    var cam = this.cams[side];
    if (!cam.stream) return;
    var recording = this.phase === "recording" || this.phase === "countdown";
    this.close(side);
    cam.select.value = "";
    cam.problem = "The " + side + " camera stopped (unplugged, or taken by another program).";
    cam.state.textContent = cam.problem + " Reconnect it and choose it again.";
    if (recording) this.abortRecording(cameraStopped(side));
    this.updateGate();
    this.listDevices();
  };

  // -- the live quality gate ------------------------------------------------------------

  Station.prototype.measure = function (cam) {
    var now = performance.now();
    var fps = null, lost = null;
    var stats = cam.track && cam.track.stats;
    if (stats && typeof stats.totalFrames === "number") {
      cam.statsLog.push({ at: now, total: stats.totalFrames, discarded: stats.discardedFrames });
      while (cam.statsLog.length > 2 && now - cam.statsLog[0].at > FPS_WINDOW_MS) cam.statsLog.shift();
      var first = cam.statsLog[0], last = cam.statsLog[cam.statsLog.length - 1];
      if (last.at - first.at >= 900) {
        fps = (1000 * (last.total - first.total)) / (last.at - first.at);
        lost = last.discarded - first.discarded;
      }
    }
    var frames = cam.frames;
    if (frames.length >= 3) {
      var steps = [];
      for (var i = 1; i < frames.length; i += 1) steps.push(frames[i].media_s - frames[i - 1].media_s);
      var interval = C.median(steps);
      if (fps === null && interval > 0) fps = 1 / interval;
      if (lost === null && interval > 0) {
        lost = 0;
        steps.forEach(function (s) { if (s >= 1.5 * interval) lost += Math.max(1, Math.round(s / interval) - 1); });
      }
    }
    return { fps: fps, lost: lost };
  };

  Station.prototype.look = function (cam) {
    var video = cam.video;
    var w = video.videoWidth, h = video.videoHeight;
    if (!w || !h || video.readyState < 2) return null;
    var scale = Math.min(1, ANALYSED_WIDTH / w);
    var sw = Math.max(1, Math.round(w * scale)), sh = Math.max(1, Math.round(h * scale));
    if (this.canvas.width !== sw || this.canvas.height !== sh) { this.canvas.width = sw; this.canvas.height = sh; }
    this.ctx.drawImage(video, 0, 0, sw, sh);
    var pixels = this.ctx.getImageData(0, 0, sw, sh).data;
    return C.analyseLuma(C.lumaOf(pixels, sw * sh), sw, sh, sw / w);
  };

  Station.prototype.tick = function () {
    var self = this;
    var recording = this.phase === "recording";
    this.lookTurn = 1 - this.lookTurn;
    SIDES.forEach(function (side, i) {
      var cam = self.cams[side];
      if (cam.track && cam.track.readyState === "ended") { self.cameraLost(side); return; }
      if (!cam.stream || cam.problem) return;
      if (self.phase === "finishing") return; // the recorders are closing their files
      // While recording, each camera's picture is looked at on every other tick (twice a
      // second): half the work, for the recorders; its frame counters are read every tick.
      var seen = recording && i !== self.lookTurn ? undefined : self.look(cam);
      var rate = self.measure(cam);
      cam.gate = { seen: seen === undefined && cam.gate ? cam.gate.seen : seen, fps: rate.fps, lost: rate.lost };
      if (recording && seen && self.take) {
        self.take.seen[side].push({ t_s: (performance.now() - self.take.startedAt) / 1000, markers: seen.markers });
      }
      self.showFacts(cam);
    });
    if (this.phase === "setup") {
      this.judgeOrder();
      this.updateGate();
    } else if (recording) {
      this.recordingGate();
    }
  };

  /** One look at both views on whether the cameras are swapped: the spots fit the rig's
   * geometry (its calibration) as chosen, exchanged, or neither clearly. Only a clear,
   * repeated "exchanged" with never a clear "as chosen" calls them swapped. */
  Station.prototype.judgeOrder = function () {
    var l = this.cams.left.gate, r = this.cams.right.gate;
    if (!this.geometry || !l || !r || !l.seen || !r.seen) return;
    var ev = C.swapEvidence(this.geometry, l.seen.spots, r.seen.spots);
    if (!ev) return;
    var fits = function (a, b) { return a <= SWAP_FIT_PX && b >= Math.max(SWAP_MISFIT_PX, 3 * a); };
    ev.says = fits(ev.swapped_px, ev.chosen_px) ? "swapped" : fits(ev.chosen_px, ev.swapped_px) ? "chosen" : "";
    this.orderLog.push(ev);
    if (this.orderLog.length > SWAP_LOOKS) this.orderLog.shift();
    var swapped = this.orderLog.filter(function (e) { return e.says === "swapped"; });
    var chosen = this.orderLog.filter(function (e) { return e.says === "chosen"; });
    this.swapped = swapped.length >= SWAP_AGREE && !chosen.length
      ? {
        chosen_px: C.median(swapped.map(function (e) { return e.chosen_px; })),
        swapped_px: C.median(swapped.map(function (e) { return e.swapped_px; })),
      }
      : null;
  };

  /** What the gate says while recording: a view that has lost its markers, frames lost. */
  Station.prototype.recordingGate = function () {
    var self = this, take = this.take;
    if (!take) return;
    var nowS = (performance.now() - take.startedAt) / 1000;
    var notes = [];
    SIDES.forEach(function (side) {
      var cam = self.cams[side], seen = take.seen[side];
      if (self.markersExpected && seen.length) {
        var gaps = C.markerGaps(seen, self.markersExpected, nowS);
        if (gaps.current_s >= UNSEEN_LIVE_S) {
          notes.push("the " + side + " camera has not seen " + self.markerWords(seen[seen.length - 1].markers)
            + " for " + Math.floor(gaps.current_s) + " s");
        }
      }
      if (cam.gate && cam.gate.lost !== null && cam.gate.lost > MAX_LOST) {
        notes.push("the " + side + " camera lost " + cam.gate.lost + " frames in the last 2 s");
      }
    });
    var text = notes.length
      ? "Recording, but check: " + notes.join("; ") + "."
      : "Recording: " + (this.markersExpected ? "both cameras see the " + this.markersExpected + " markers." : "both cameras run.");
    this.showGate(text, notes.length ? "not-ready" : "ready");
  };

  /** "the 2 markers", or "all 3 markers" when some are seen. */
  Station.prototype.markerWords = function (seen) {
    var n = this.markersExpected;
    return seen > 0 ? (n === 2 ? "both markers" : "all " + n + " markers") : "the markers";
  };

  /** The quick check's objections to the views (from the looks while recording): a camera
   * that did not see every marker for a substantial part of the take. */
  Station.prototype.unseenProblems = function (take, lengthS) {
    var self = this, problems = [];
    if (!this.markersExpected || !take.seen) return problems;
    SIDES.forEach(function (side) {
      var seen = take.seen[side];
      if (!seen.length) return;
      var gaps = C.markerGaps(seen, self.markersExpected, lengthS);
      if (gaps.missing_s < Math.max(UNSEEN_TAKE_S, UNSEEN_TAKE_SHARE * lengthS)) return;
      var some = seen.some(function (s) { return s.markers > 0 && s.markers < self.markersExpected; });
      problems.push("the " + side + " camera did not see " + (some ? "every marker" : "the markers") + " for "
        + gaps.missing_s.toFixed(1) + " s of the " + lengthS.toFixed(1) + " s"
        + (gaps.longest ? " (the longest stretch from " + gaps.longest.start_s.toFixed(1) + " s to "
          + gaps.longest.end_s.toFixed(1) + " s)" : "")
        + ": keep every marker in both views, lit by the ring light");
    });
    return problems;
  };

  Station.prototype.showFacts = function (cam) {
    var g = cam.gate;
    var fact = function (name) { return $(cam.view, '[data-fact="' + name + '"]'); };
    fact("fps").textContent = g.fps ? g.fps.toFixed(1) + " fps" : "measuring…";
    fact("dropped").textContent = g.lost === null ? "–" : String(g.lost);
    if (g.seen) {
      if (fact("markers")) fact("markers").textContent = String(g.seen.markers);
      if (fact("clipped")) fact("clipped").textContent = String(g.seen.clipped);
      fact("saturated").textContent = (100 * g.seen.saturated).toFixed(1) + " %";
    }
    var notes = [];
    var name = "the " + cam.side + " camera";
    if (g.seen && this.markersExpected) {
      if (g.seen.markers < this.markersExpected) {
        notes.push(name + " sees " + g.seen.markers + " marker" + (g.seen.markers === 1 ? "" : "s")
          + " of " + this.markersExpected + " (every marker of the task must be in its view, lit by the ring light)");
      } else if (g.seen.markers > this.markersExpected) {
        notes.push(name + " sees " + g.seen.markers + " bright marker-like spots, " + this.markersExpected
          + " expected (remove reflections: rings, watch, shiny objects)");
      }
      if (g.seen.clipped) notes.push(name + " has a bright spot cut by the image border (move the hand or the camera so the markers stay inside)");
    }
    if (g.seen && g.seen.saturated > MAX_WHITE) {
      notes.push(name + " is over-exposed (" + (100 * g.seen.saturated).toFixed(0) + " % of the picture is white: shorten the exposure or dim the light)");
    }
    cam.tooSlow = g.fps !== null && g.fps < MIN_FPS
      ? capital(name) + " delivers only " + g.fps.toFixed(0) + " frames per second; at least " + MIN_FPS
        + " are needed (60 or more is advised): choose a faster camera mode or better light."
      : null;
    if (g.lost !== null && g.lost > MAX_LOST) {
      notes.push(name + " lost " + g.lost + " frames in the last 2 s (close other programs; give each camera a USB port of its own)");
    }
    cam.notes = notes;
    cam.slow = g.fps !== null && g.fps < ADVISED_FPS;
    cam.state.textContent = notes.length ? capital(notes.join("; ")) + "." : "Ready.";
  };

  /** The gate's verdict in words; the Start button follows it. */
  Station.prototype.updateGate = function () {
    var self = this;
    var cams = SIDES.map(function (s) { return self.cams[s]; });
    var hard = [], soft = [];
    var found = this.noCamera ? 0 : this.listed ? this.devices.length : null; // null: not listed yet
    if (found === 0) hard.push("No camera was found; connect the two cameras.");
    else if (found === 1) hard.push("Only one camera was found; connect the second camera (it then appears in the lists).");
    cams.forEach(function (cam) {
      if (cam.problem) hard.push(cam.problem);
      else if (!cam.deviceId) { if (found === null || found > 1) hard.push("Choose the " + cam.side + " camera."); }
      else if (!cam.stream) hard.push("The " + cam.side + " camera is starting.");
      else if (!cam.gate) hard.push("Measuring the " + cam.side + " camera…");
      else if (cam.tooSlow) hard.push(cam.tooSlow);
      soft = soft.concat(cam.problem ? [] : cam.notes);
    });
    if (this.swapped) {
      soft.unshift("the cameras look swapped: the markers fit the rig's calibration with the left and right"
        + " cameras exchanged (" + this.swapped.swapped_px.toFixed(1) + " px off) and not as chosen ("
        + this.swapped.chosen_px.toFixed(1) + " px off); choose the rig's left camera as “Left camera”"
        + " and its right camera as “Right camera”");
    }
    var text, state;
    if (hard.length) {
      text = "Not ready: " + hard.join(" ");
      state = "not-ready";
    } else if (soft.length) {
      text = "Not ready: " + soft.join("; ") + ". You can still record, but the analysis may fail.";
      state = "not-ready";
    } else {
      var rates = cams.map(function (c) { return c.gate.fps ? c.gate.fps.toFixed(0) : "?"; });
      text = "Ready: "
        + (this.markersExpected
          ? "both cameras see the " + this.markersExpected + " markers, "
          : this.mode === "trial"
            ? "both cameras run (the gate does not count this task's markers; the analysis does), "
            : "both cameras run, ")
        + rates.join(" and ") + " frames per second."
        + (cams.some(function (c) { return c.slow; }) ? " (60 frames per second or more measures fast taps better.)" : "");
      state = "ready";
    }
    this.showGate(text, state);
    if (this.phase === "setup") this.startButton.disabled = hard.length > 0;
  };

  Station.prototype.showGate = function (text, state) {
    var box = this.gateBox;
    if (box.textContent !== text) box.textContent = text; // unchanged: not announced again
    box.className = "gate gate-" + state;
    box.setAttribute("data-gate-state", state);
  };

  // -- recording ------------------------------------------------------------------------

  Station.prototype.setChoosing = function (enabled) {
    var self = this;
    SIDES.forEach(function (side) { self.cams[side].select.disabled = !enabled; });
    Array.prototype.forEach.call(this.form.elements, function (el) {
      if (!el.hasAttribute("data-lock-exposure")) el.disabled = !enabled;
    });
  };

  Station.prototype.countdown = function () {
    var self = this;
    if (this.phase !== "setup" || this.startButton.disabled) return;
    if (this.mode === "calibration" && !this.form.reportValidity()) return;
    this.clearError();
    this.phase = "countdown";
    this.setChoosing(false);
    this.startButton.disabled = true;
    this.stopButton.disabled = false;
    this.stopButton.focus();
    var left = this.countdownS;
    var step = function () {
      if (self.phase !== "countdown") return;
      if (left <= 0) { self.countdownBox.textContent = "Recording."; self.record(); return; }
      self.countdownBox.textContent = "Recording starts in " + left + "…";
      left -= 1;
      self.countdownTimer = window.setTimeout(step, 1000);
    };
    step();
  };

  /** A random id of the take: sent again after a lost connection, it is not stored twice. */
  function newTakeId() {
    if (window.crypto && window.crypto.randomUUID) return window.crypto.randomUUID();
    var bytes = new Uint8Array(16);
    window.crypto.getRandomValues(bytes);
    return Array.prototype.map.call(bytes, function (b) { return (b + 256).toString(16).slice(1); }).join("");
  }

  function pickMime() {
    for (var i = 0; i < MIME_TYPES.length; i += 1) {
      if (window.MediaRecorder.isTypeSupported(MIME_TYPES[i])) return MIME_TYPES[i];
    }
    return "";
  }

  Station.prototype.record = function () {
    var self = this;
    var mime = pickMime();
    var durationS = Math.max(2, Math.min(120, Number(this.form.elements.duration_s.value) || 15));
    var take = {
      id: newTakeId(), mime: mime, durationS: durationS, recorders: {}, chunks: {}, stopped: [],
      seen: { left: [], right: [] }, // {t_s, markers} of each look at a view while recording
    };
    try {
      SIDES.forEach(function (side) {
        var cam = self.cams[side];
        var size = cam.size || { w: 1280, h: 720 };
        var fps = (cam.gate && cam.gate.fps) || 30;
        var bits = Math.max(4e6, Math.min(40e6, 0.3 * size.w * size.h * fps)); // markers keep their shape
        var options = { videoBitsPerSecond: Math.round(bits) };
        if (mime) options.mimeType = mime;
        var recorder = new MediaRecorder(cam.stream, options);
        take.chunks[side] = [];
        recorder.addEventListener("dataavailable", function (e) { if (e.data && e.data.size) take.chunks[side].push(e.data); });
        take.stopped.push(new Promise(function (resolve) { recorder.addEventListener("stop", resolve); }));
        recorder.addEventListener("error", function () { self.abortRecording(cameraStopped(side, "the " + side + " camera's recorder failed")); });
        take.recorders[side] = recorder;
      });
    } catch (error) {
      this.take = null;
      this.phase = "setup";
      this.setChoosing(true);
      this.stopButton.disabled = true;
      this.countdownBox.textContent = "";
      this.showError("This browser could not start recording (" + error.message + ").", false);
      this.updateGate();
      return;
    }
    this.take = take;
    SIDES.forEach(function (side) { self.cams[side].log = []; });
    SIDES.forEach(function (side) { take.recorders[side].start(1000); });
    take.startedAt = performance.now();
    this.phase = "recording";
    this.timer = window.setInterval(function () {
      var elapsed = (performance.now() - take.startedAt) / 1000;
      self.timerBox.textContent = elapsed.toFixed(1) + " s of " + durationS + " s";
      if (elapsed >= durationS) self.stopRecording();
    }, 100);
  };

  Station.prototype.stopTimers = function () {
    window.clearTimeout(this.countdownTimer);
    window.clearInterval(this.timer);
  };

  /** The take is dropped while recording; ``message`` says why and what to do. */
  Station.prototype.abortRecording = function (message) {
    var take = this.take;
    this.stopTimers();
    if (take) {
      SIDES.forEach(function (s) {
        var r = take.recorders[s];
        if (r && r.state !== "inactive") { try { r.stop(); } catch (e) { /* already stopped */ } }
      });
    }
    this.take = null;
    SIDES.forEach(function (s) { this.cams[s].log = null; }, this);
    this.phase = "setup";
    this.setChoosing(true);
    this.stopButton.disabled = true;
    this.countdownBox.textContent = "";
    this.showError(message, false);
    this.updateGate();
  };

  function cameraStopped(side, why) {
    return capital(why || "the " + side + " camera stopped during the recording (unplugged, or taken by another program)")
      + ". The take was discarded and nothing was stored. Reconnect the camera, choose it again and record again.";
  }

  /** A hidden page (another tab or window in front, the screen locked) is slowed down by
   * the browser: its timers and its frame log stall and the cameras lose frames. A take
   * under way is stopped and dropped, a countdown cancelled, each with a sentence. */
  Station.prototype.pageHidden = function () {
    if (document.visibilityState !== "hidden") return;
    if (this.phase === "countdown") {
      this.stopRecording(); // nothing was recorded yet
      this.showError("The page was hidden before the recording started, so it did not start. Keep this page"
        + " in front (no other tab or window over it) and press “Start recording” again.", false);
    } else if (this.phase === "recording") {
      this.abortRecording("The page was hidden during the recording (another tab or window was brought in"
        + " front, or the screen locked): the browser slows a hidden page down and the cameras lose frames."
        + " The take was discarded and nothing was stored. Keep this page in front and record again.");
    }
  };

  Station.prototype.stopRecording = function () {
    var self = this;
    if (this.phase === "countdown") { // stopped before it began: nothing was recorded
      this.stopTimers();
      this.phase = "setup";
      this.setChoosing(true);
      this.stopButton.disabled = true;
      this.countdownBox.textContent = "";
      this.updateGate();
      this.startButton.focus();
      return;
    }
    if (this.phase !== "recording") return;
    var take = this.take;
    var lengthS = (performance.now() - take.startedAt) / 1000;
    take.stoppedEarly = lengthS < take.durationS - 0.25;
    take.unseen = this.unseenProblems(take, lengthS);
    this.phase = "finishing";
    this.stopTimers();
    this.stopButton.disabled = true;
    this.countdownBox.textContent = "Stopped.";
    SIDES.forEach(function (side) { take.recorders[side].stop(); });
    Promise.all(take.stopped)
      .then(function () {
        if (self.take !== take) return null;
        take.logs = {};
        SIDES.forEach(function (side) { take.logs[side] = self.cams[side].log || []; self.cams[side].log = null; });
        return self.finishTake(take);
      })
      .then(function () {
        if (self.take !== take) return;
        // A stretch without frames that the server would refuse: said now, not after the upload.
        var hole = null;
        SIDES.forEach(function (side) {
          if (!hole && take.timedByFile[side]) hole = C.holeSentence(side, take.facts[side], self.holeS, self.holeFrames);
        });
        if (hole) { self.endTake(hole, false); return; } // nothing to send: only "Retake"
        self.upload();
      })
      .catch(function (error) {
        if (self.take !== take) return;
        self.phase = "done";
        self.afterBox.hidden = false;
        self.showError("The take could not be prepared for upload (" + error.message + "); nothing was stored. Press “Retake”.", false);
      });
  };

  /** The files of the take and its quick check, from the recorded bytes and capture times. */
  Station.prototype.finishTake = function (take) {
    var self = this;
    var webm = take.mime.indexOf("webm") >= 0 || !take.mime;
    var ext = take.mime.indexOf("mp4") >= 0 ? ".mp4" : ".webm";
    take.files = {};
    take.facts = {};
    take.timedByFile = {}; // facts from the recorded file's own frame times, not the page's log
    return Promise.all(SIDES.map(function (side) {
      var blob = new Blob(take.chunks[side], { type: take.mime || "video/webm" });
      take.files[side + "_video"] = new File([blob], side + ext, { type: blob.type });
      if (!webm) {
        take.facts[side] = C.takeFacts(take.logs[side]);
        return null;
      }
      return blob.arrayBuffer().then(function (buffer) {
        var stamps = C.webmFrameTimesMs(buffer);
        var aligned = stamps && C.alignFrameTimes(stamps, take.logs[side]);
        if (aligned) {
          take.files[side + "_times"] = new File([C.timesCsv(aligned.times_s)], side + "_times.csv", { type: "text/csv" });
          take.facts[side] = C.takeFacts(aligned.times_s);
          take.timedByFile[side] = true;
        } else if (stamps && stamps.length) {
          take.facts[side] = C.takeFacts(stamps.map(function (ms) { return ms / 1000; }));
          take.timedByFile[side] = true;
        } else {
          take.facts[side] = C.takeFacts(take.logs[side]);
        }
        return null;
      });
    })).then(function () { self.showTake(take.facts, false); });
  };

  Station.prototype.showTake = function (facts, checked) {
    var rows = $(this.takeBox, "[data-take-rows]");
    rows.textContent = "";
    var problems = [];
    var self = this;
    SIDES.forEach(function (side) {
      var f = facts[side];
      if (!f) return;
      var tr = document.createElement("tr");
      tr.setAttribute("data-take-side", side);
      var cells = [
        capital(side),
        String(f.frame_count),
        f.duration_s.toFixed(1) + " s",
        f.fps.toFixed(1) + " fps",
        f.dropped_frames === null || f.dropped_frames === undefined ? "–" : String(f.dropped_frames),
      ];
      cells.forEach(function (text, i) {
        var cell = document.createElement(i === 0 ? "th" : "td");
        if (i === 0) cell.scope = "row"; else cell.className = "num";
        cell.textContent = text;
        tr.appendChild(cell);
      });
      rows.appendChild(tr);
      if (f.dropped_frames > MAX_LOST) problems.push("the " + side + " camera lost " + f.dropped_frames + " frames");
      if (f.fps < MIN_FPS) problems.push("the " + side + " camera reached only " + f.fps.toFixed(1) + " frames per second (at least " + MIN_FPS + " needed)");
      if (self.take && f.duration_s < 0.8 * self.take.durationS && self.take.durationS && !self.take.stoppedEarly) {
        problems.push("the " + side + " recording is " + f.duration_s.toFixed(1) + " s long");
      }
    });
    if (facts.left && facts.right && Math.abs(facts.left.duration_s - facts.right.duration_s) > 0.5) {
      problems.push("the two recordings differ in length by " + Math.abs(facts.left.duration_s - facts.right.duration_s).toFixed(1) + " s");
    }
    if (this.take && this.take.unseen) problems = problems.concat(this.take.unseen); // the page's own looks
    var verdict = $(this.takeBox, "[data-take-verdict]");
    verdict.textContent = (problems.length
      ? "Check the take: " + problems.join("; ") + ". Consider a retake."
      : "The take looks complete.") + (checked ? " (Checked by the server.)" : "");
    verdict.className = "take-verdict " + (problems.length ? "warn-text" : "");
    this.takeBox.hidden = false;
  };

  // -- upload and the analysis ------------------------------------------------------------

  Station.prototype.formData = function () {
    var data = new FormData();
    data.append("csrf_token", this.csrf);
    var form = this.form;
    if (this.mode === "trial") {
      data.append("hand", form.elements.hand.value);
      if (form.elements.task) data.append("task", form.elements.task.value);
      if (this.trialRigId) data.append("rig_id", this.trialRigId);
      data.append("take_id", this.take.id);
    } else {
      ["board", "dictionary", "cols", "rows", "square_mm", "marker_mm"].forEach(function (name) {
        var value = form.elements[name].value.trim();
        if (value) data.append(name, value);
      });
    }
    var files = this.take.files;
    Object.keys(files).forEach(function (name) { data.append(name, files[name], files[name].name); });
    return data;
  };

  /** The take is not stored: ``message`` says why; ``again`` offers "Upload again" beside "Retake". */
  Station.prototype.endTake = function (message, again) {
    this.phase = "done";
    this.uploadBlock.hidden = true;
    this.afterBox.hidden = false;
    this.uploadAgainButton.hidden = !again;
    this.showError(message, false);
  };

  Station.prototype.upload = function () {
    var self = this;
    var take = this.take;
    if (!take || !take.files) return;
    this.clearError();
    this.phase = "uploading";
    this.afterBox.hidden = true;
    this.uploadAgainButton.hidden = true;
    this.uploadBlock.hidden = false;
    this.uploadBar.value = 0;
    this.uploadText.textContent = "Sending the take…";
    var xhr = new XMLHttpRequest();
    xhr.open("POST", this.uploadUrl);
    xhr.setRequestHeader("Accept", "application/json");
    xhr.setRequestHeader("X-CSRF-Token", this.csrf);
    xhr.upload.addEventListener("progress", function (e) {
      if (!e.lengthComputable) return;
      var pct = Math.round((100 * e.loaded) / e.total);
      self.uploadBar.value = pct;
      self.uploadBar.textContent = pct + " %";
      self.uploadText.textContent = pct + " % sent (" + (e.loaded / 1e6).toFixed(1) + " of " + (e.total / 1e6).toFixed(1) + " MB)";
    });
    var sent = false; // every byte of the take left the browser
    xhr.upload.addEventListener("load", function () {
      sent = true;
      self.uploadText.textContent = "Sent. The server checks the videos…";
    });
    var failed = function (message, again) { if (self.take === take) self.endTake(message, again); };
    xhr.addEventListener("load", function () {
      var body = null;
      try { body = JSON.parse(xhr.responseText); } catch (e) { body = null; }
      if (xhr.status === 401) {
        failed("Your login has expired; nothing of this take was stored. Log in again in another tab, then press “Upload again”.", true);
        return;
      }
      if (xhr.status >= 200 && xhr.status < 300 && body && body.job_id) {
        self.uploaded(body);
        return;
      }
      var said = body && window.BradyscopeApp ? window.BradyscopeApp.errorText(body.detail) : null;
      var detail = said || "The upload failed (status " + xhr.status + ").";
      failed(detail + " Nothing of this take was stored.", xhr.status >= 500 || xhr.status === 0);
    });
    var lost = function () {
      if (!sent) { // a body cut off midway is discarded by the server
        failed("The connection was lost during the upload; nothing of this take was stored. Press “Upload again” to send it again, or “Retake”.", true);
      } else if (self.mode === "trial") {
        failed("The connection was lost after the take was sent, while the server checked it: it may have been stored. Press “Upload again”: a take the server stored already is not stored twice.", true);
      } else {
        failed("The connection was lost after the board videos were sent, while the server checked them: they may have been stored. Look at the rig page's calibrations before you press “Upload again”.", true);
      }
    };
    xhr.addEventListener("error", lost);
    xhr.addEventListener("abort", lost);
    xhr.send(this.formData());
  };

  Station.prototype.uploaded = function (body) {
    var self = this;
    this.phase = "done";
    this.take.stored = true;
    this.uploadText.textContent = body.stored_before
      ? "The server had stored this take already (before the connection was lost); it was not stored twice."
      : "Stored. The analysis has started.";
    this.uploadBar.value = 100;
    if (body.take && body.take.left) this.showTake(body.take, true);
    var job = $(this.takeBox, "[data-job]");
    job.hidden = false;
    $(job, "[data-job-link]").href = body.job_url;
    this.afterBox.hidden = false;
    this.retakeButton.focus();
    var statusEl = $(job, "[data-job-status]"), stageEl = $(job, "[data-job-stage]");
    var bar = $(job, "[data-job-progress]"), errorEl = $(job, "[data-job-error]");
    var take = this.take;
    var poll = function () {
      if (self.take !== take) return; // a retake: the stored trial is measured on; its job page tells
      fetch("/jobs/" + body.job_id + "/status", { headers: { Accept: "application/json" }, credentials: "same-origin", cache: "no-store" })
        .then(function (r) { return r.ok ? r.json() : null; })
        .then(function (s) {
          if (!s) { window.setTimeout(poll, 3000); return; }
          statusEl.textContent = s.status;
          statusEl.className = "status status-" + s.status;
          stageEl.textContent = s.stage_label || s.stage || "";
          var pct = s.status === "succeeded" ? 100 : Math.round(100 * (s.progress || 0));
          bar.value = pct; bar.textContent = pct + " %";
          job.setAttribute("data-status", s.status);
          if (s.status === "failed") { errorEl.textContent = s.error || "The job failed."; errorEl.hidden = false; }
          if (s.status === "succeeded" && (s.trial_url || s.rig_url)) {
            var link = $(job, "[data-result-link]");
            link.href = s.trial_url || s.rig_url;
            $(job, "[data-result-link-wrap]").hidden = false;
          }
          if (s.status === "queued" || s.status === "running") window.setTimeout(poll, 1000);
        })
        .catch(function () { window.setTimeout(poll, 3000); });
    };
    poll();
  };

  Station.prototype.retake = function () {
    if (this.phase === "uploading" || this.phase === "recording" || this.phase === "finishing") return;
    this.take = null; // what was stored stays stored; an unsent take is dropped
    this.phase = "setup";
    this.clearError();
    this.afterBox.hidden = true;
    this.takeBox.hidden = true;
    $(this.takeBox, "[data-job]").hidden = true;
    $(this.takeBox, "[data-job-error]").hidden = true;
    $(this.takeBox, "[data-result-link-wrap]").hidden = true;
    this.uploadBlock.hidden = true;
    this.countdownBox.textContent = "";
    this.timerBox.textContent = "0.0 s";
    this.setChoosing(true);
    this.updateGate();
    this.startButton.focus();
  };

  document.addEventListener("DOMContentLoaded", function () {
    var root = document.querySelector("[data-capture]");
    if (root && C) new Station(root).start();
  });
})();
