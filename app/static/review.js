// bradyscope review view: both videos in step with the tracked markers drawn on them, the
// aperture curve with a cursor at the videos' time. Plain JavaScript, no library, no inline code.
//
// Frame numbers are each video's own. A proxy holds frame i at its capture time from the
// video's first frame (overlay.cameras[].time_s: irregular intervals and lost frames kept;
// i / fps in overlays without it); the signal, taps and pauses are at the analysis's times
// of the left frames (data.time_s). The left video leads; the right one is kept on the frame the time model pairs with the left frame
// (overlay.cameras[].left_frame). Overlay pixels are OpenCV's (centre of the top-left pixel
// at 0, 0): a canvas pixel i spans [i, i + 1), so a point x is drawn at x + 0.5.
"use strict";

(function () {
  var OTHER = "rgb(148,103,189)";  // a marker the protocol does not name
  var DETECTION = "rgb(0,200,0)";
  var RADIUS = 6;

  // The last index i with times[i] <= t (0 before the first).
  function indexAt(times, t) {
    var lo = 0, hi = times.length - 1;
    if (hi < 0 || t < times[0]) return 0;
    while (lo < hi) {
      var mid = (lo + hi + 1) >> 1;
      if (times[mid] <= t) lo = mid; else hi = mid - 1;
    }
    return lo;
  }
  // The frame a player shows at its time, and the time to seek to for a frame (a quarter
  // of a frame into it, clear of rounding on either side).
  function frameOf(time, p) {
    return p.times ? indexAt(p.times, time + 1e-4) : Math.floor(time * p.fps + 0.001);
  }
  function seekTime(frame, p) {
    return (p.times && frame < p.times.length ? p.times[frame] : frame / p.fps) + 0.25 / p.fps;
  }

  function setup(data) {
    var fps = data.fps || 100;
    var colours = data.marker_colours || {};
    var cams = (data.overlay && data.overlay.cameras) || [];
    var players = {};
    cams.forEach(function (cam) {
      var side = cam.video || cam.camera;
      var video = document.querySelector('video[data-video="' + side + '"]');
      var canvas = document.querySelector('canvas[data-overlay="' + side + '"]');
      if (!video || !canvas) return;
      canvas.width = cam.image_size[0];
      canvas.height = cam.image_size[1];
      players[side] = { cam: cam, video: video, canvas: canvas, frame: -1, fps: cam.fps || fps, times: cam.time_s || null };
    });
    // Videos without an overlay still play (e.g. older results).
    Array.prototype.forEach.call(document.querySelectorAll("video[data-video]"), function (video) {
      var side = video.getAttribute("data-video");
      if (!players[side]) players[side] = { cam: null, video: video, canvas: null, frame: -1, fps: fps, times: null };
    });
    var leadSide = players.left && players.left.cam && players.left.cam.camera === "left" ? "left"
      : (players.right && players.right.cam && players.right.cam.camera === "left" ? "right" : "left");
    var lead = players[leadSide];
    var follow = players[leadSide === "left" ? "right" : "left"];
    if (!lead) return;
    var frameOut = document.querySelector("[data-frame-out]");
    var timeOut = document.querySelector("[data-time-out]");
    var container = document.querySelector("[data-review-player]");
    var plot = document.querySelector("canvas[data-aperture]");
    var playButton = document.querySelector('[data-action="play"]');
    // The analysis's time of each left frame, and the left frame at an analysis time.
    var leftTimes = data.time_s && data.time_s.length ? data.time_s : null;
    function timeOfFrame(i) { return leftTimes && i < leftTimes.length ? leftTimes[i] : i / fps; }
    function frameAtTime(t) {
      if (!leftTimes) return Math.round(t * fps);
      var i = indexAt(leftTimes, t);
      return i + 1 < leftTimes.length && leftTimes[i + 1] - t < t - leftTimes[i] ? i + 1 : i;
    }

    // For each lead frame, the follower frame the time model pairs with it.
    var pairing = null;
    if (follow && follow.cam && follow.cam.left_frame) {
      pairing = [];
      var lf = follow.cam.left_frame;
      var j = 0;
      var n = lead.cam ? lead.cam.frame_count : Math.ceil(lead.video.duration * fps);
      for (var i = 0; i < n; i++) {
        while (j + 1 < lf.length && lf[j + 1] !== null && Math.abs(lf[j + 1] - i) <= Math.abs((lf[j] === null ? 1e9 : lf[j]) - i)) j++;
        pairing.push(lf[j] !== null && Math.abs(lf[j] - i) <= 1 ? j : null);
      }
    }

    function draw(p, frame) {
      p.frame = frame;
      p.video.setAttribute("data-frame", String(frame));
      if (!p.canvas || !p.cam) return;
      var ctx = p.canvas.getContext("2d");
      ctx.clearRect(0, 0, p.canvas.width, p.canvas.height);
      var dets = p.cam.detections[frame] || [];
      ctx.strokeStyle = DETECTION;
      ctx.lineWidth = 1;
      dets.forEach(function (d) {
        if (!d) return;
        var x = d[0] + 0.5, y = d[1] + 0.5;
        ctx.beginPath();
        ctx.moveTo(x - 12, y); ctx.lineTo(x - 8, y);
        ctx.moveTo(x + 8, y); ctx.lineTo(x + 12, y);
        ctx.moveTo(x, y - 12); ctx.lineTo(x, y - 8);
        ctx.moveTo(x, y + 8); ctx.lineTo(x, y + 12);
        ctx.stroke();
      });
      var shown = [];
      Object.keys(p.cam.tracks).forEach(function (name) {
        var pt = p.cam.tracks[name][frame];
        if (pt) shown.push({ name: name, x: pt[0] + 0.5, y: pt[1] + 0.5 });
      });
      // Each label on the side of its dot away from the others' middle, so that no label
      // covers a neighbouring dot (markers of one hand are a few dot sizes apart).
      var mx = 0, my = 0;
      shown.forEach(function (s) { mx += s.x / shown.length; my += s.y / shown.length; });
      ctx.font = "bold 14px sans-serif";
      shown.forEach(function (s) {
        ctx.fillStyle = colours[s.name] || OTHER;
        ctx.beginPath();
        ctx.arc(s.x, s.y, RADIUS, 0, 2 * Math.PI);
        ctx.fill();
        var dx = s.x - mx, dy = s.y - my, len = Math.sqrt(dx * dx + dy * dy);
        if (shown.length < 2 || len < 1) { dx = 0.7071; dy = -0.7071; len = 1; }
        var lx = s.x + 18 * dx / len, ly = s.y + 18 * dy / len;
        ctx.textAlign = dx < -0.3 * len ? "right" : (dx > 0.3 * len ? "left" : "center");
        ctx.textBaseline = dy < -0.3 * len ? "bottom" : (dy > 0.3 * len ? "top" : "middle");
        ctx.fillStyle = "rgb(255,255,255)";
        ctx.fillText(s.name, lx, ly);
      });
      ctx.textAlign = "start";
      ctx.textBaseline = "alphabetic";
    }

    function time() { return lead.video.currentTime; }

    function show(frame) {
      draw(lead, frame);
      if (follow) {
        var j = pairing ? pairing[frame] : frame;
        if (j === null || j === undefined) {
          if (follow.canvas) follow.canvas.getContext("2d").clearRect(0, 0, follow.canvas.width, follow.canvas.height);
        } else {
          if (follow.video.paused || Math.abs(frameOf(follow.video.currentTime, follow) - j) > 1) {
            if (lead.video.paused) follow.video.currentTime = seekTime(j, follow);
            else if (Math.abs(frameOf(follow.video.currentTime, follow) - j) > 2) follow.video.currentTime = seekTime(j, follow);
          }
          // A follow video that was just asked to seek still shows its old frame: its
          // overlay is drawn when the seek lands ("seeked" below), not ahead of its picture.
          if (follow.video.paused && !follow.video.seeking) draw(follow, j);
        }
      }
      var t = timeOfFrame(frame);
      if (frameOut) frameOut.textContent = String(frame);
      if (timeOut) timeOut.textContent = t.toFixed(3);
      if (container) { container.setAttribute("data-frame", String(frame)); container.setAttribute("data-time", t.toFixed(4)); }
      drawPlot(t);
    }

    // The frame last asked for: keys pressed faster than the video seeks step on from it,
    // not from the frame still on screen (three presses move three frames).
    var pending = null;
    function current() { return pending === null ? lead.frame : pending; }

    function seekFrame(frame) {
      var max = lead.cam ? lead.cam.frame_count - 1 : Math.floor(lead.video.duration * fps) - 1;
      frame = Math.max(0, Math.min(max, frame));
      lead.video.pause();
      if (follow) follow.video.pause();
      pending = frame;
      lead.video.currentTime = seekTime(frame, lead);
    }

    lead.video.addEventListener("seeked", function () {
      if (!lead.video.seeking) pending = null;  // the last seek asked for has landed
      show(frameOf(lead.video.currentTime, lead));
    });
    if (follow) follow.video.addEventListener("seeked", function () {
      if (follow.video.paused) draw(follow, frameOf(follow.video.currentTime, follow));
    });
    lead.video.addEventListener("loadeddata", function () { show(frameOf(lead.video.currentTime, lead)); });

    function onFrame(p, isLead) {
      if (!p.video.requestVideoFrameCallback) return;
      var cb = function (now, meta) {
        var frame = frameOf(meta.mediaTime, p);
        if (isLead) show(frame); else draw(p, frame);
        p.video.requestVideoFrameCallback(cb);
      };
      p.video.requestVideoFrameCallback(cb);
    }
    onFrame(lead, true);
    if (follow) onFrame(follow, false);
    lead.video.addEventListener("timeupdate", function () {
      if (!lead.video.requestVideoFrameCallback) show(frameOf(time(), lead));
    });

    // The frame readout is announced while paused (stepping, jumping to a tap), not 100
    // times a second while playing.
    var readout = frameOut ? frameOut.closest("[aria-live]") : null;
    function announce(on) { if (readout) readout.setAttribute("aria-live", on ? "polite" : "off"); }
    announce(true);
    function togglePlay() {
      if (lead.video.paused) {
        pending = null;
        announce(false);
        var p = lead.video.play();
        if (follow) follow.video.play();
        if (p && p.catch) p.catch(function () {});
        playButton.textContent = "Pause";
      } else {
        lead.video.pause();
        if (follow) follow.video.pause();
        playButton.textContent = "Play";
        announce(true);
        show(frameOf(time(), lead));
      }
    }
    lead.video.addEventListener("ended", function () {
      announce(true);
      playButton.textContent = "Play";
      if (follow) follow.video.pause();
    });
    playButton.addEventListener("click", togglePlay);
    document.querySelector('[data-action="prev"]').addEventListener("click", function () { seekFrame(current() - 1); });
    document.querySelector('[data-action="next"]').addEventListener("click", function () { seekFrame(current() + 1); });
    document.addEventListener("keydown", function (e) {
      var tag = (e.target && e.target.tagName) || "";
      if (/^(INPUT|TEXTAREA|SELECT|BUTTON|A)$/.test(tag)) return;
      if (e.key === " ") { e.preventDefault(); togglePlay(); }
      else if (e.key === "ArrowLeft") { e.preventDefault(); seekFrame(current() - 1); }
      else if (e.key === "ArrowRight") { e.preventDefault(); seekFrame(current() + 1); }
    });
    Array.prototype.forEach.call(document.querySelectorAll("[data-jump]"), function (b) {
      b.addEventListener("click", function () {
        seekFrame(frameAtTime(parseFloat(b.getAttribute("data-jump"))));
        if (container) container.scrollIntoView({ block: "nearest" });
      });
    });

    // ------------------------------------------------------------------ the signal plot
    // The task's cycle signal (finger tapping: the aperture), in data.unit (mm or deg).
    var ap = data.signal || [];
    var peakKey = data.peak_key || "t_max_aperture_s";
    var duration = (ap.length ? timeOfFrame(ap.length - 1) + 1 / fps : 0) || lead.video.duration || 1;
    var ymax = 0;
    ap.forEach(function (v) { if (v !== null && v > ymax) ymax = v; });
    ymax = ymax * 1.1 || 1;
    // Ticks every 1, 2 or 5 x 10^k units: five to ten of them, in mm or degrees.
    var yStep = Math.pow(10, Math.floor(Math.log(ymax / 5) / Math.LN10));
    if (ymax / yStep > 25) yStep *= 5; else if (ymax / yStep > 10) yStep *= 2;
    var pad = { l: 48, r: 10, t: 10, b: 28 };
    // Drawn in CSS pixels at the size it is shown (W x H), on a backing store of the
    // screen's pixel density: the words keep their size on a narrow screen and stay sharp.
    var W = 1200, H = 260, lastCursor = 0;
    function fit() {
      if (!plot) return;
      var dpr = window.devicePixelRatio || 1;
      W = Math.max(320, Math.round(plot.getBoundingClientRect().width || 1200));
      H = Math.round(Math.min(260, Math.max(200, W * 0.3)));
      plot.width = Math.round(W * dpr);
      plot.height = Math.round(H * dpr);
      plot.getContext("2d").setTransform(dpr, 0, 0, dpr, 0, 0);
    }
    function X(t) { return pad.l + (W - pad.l - pad.r) * t / duration; }
    function Y(v) { return H - pad.b - (H - pad.t - pad.b) * v / ymax; }
    function band(ctx, t0, t1, color, dashed) {
      ctx.fillStyle = color;
      ctx.fillRect(X(t0), pad.t, Math.max(1, X(t1) - X(t0)), H - pad.t - pad.b);
      if (dashed) {
        ctx.setLineDash([4, 3]); ctx.strokeStyle = "rgb(120,120,120)";
        ctx.strokeRect(X(t0), pad.t, Math.max(1, X(t1) - X(t0)), H - pad.t - pad.b);
        ctx.setLineDash([]);
      }
    }
    function drawPlot(cursor) {
      if (!plot) return;
      lastCursor = cursor;
      var ctx = plot.getContext("2d");
      ctx.clearRect(0, 0, W, H);
      (data.events || []).forEach(function (e) {
        var c = e.kind === "halt" ? "rgba(214,39,40,0.25)" : e.kind === "hesitation" ? "rgba(255,165,0,0.3)" : "rgba(128,128,128,0.25)";
        band(ctx, e.t_start_s, e.t_start_s + Math.max(e.duration_s, 0.02), c, false);
      });
      (data.dismissed_events || []).forEach(function (e) {
        band(ctx, e.t_start_s, e.t_start_s + Math.max(e.duration_s, 0.02), "rgba(200,200,200,0.15)", true);
      });
      (data.taps || []).forEach(function (tp) { band(ctx, tp.t_start_s, tp.t_end_s, "rgba(31,119,180,0.08)", false); });
      (data.excluded_taps || []).concat(data.outside_window_taps || []).forEach(function (tp) {
        band(ctx, tp.t_start_s, tp.t_end_s, "rgba(90,90,90,0.2)", true);
      });
      if (data.window_s) {
        ctx.strokeStyle = "rgb(0,0,0)"; ctx.setLineDash([6, 4]);
        [data.window_s[0], data.window_s[1]].forEach(function (t) { ctx.beginPath(); ctx.moveTo(X(t), pad.t); ctx.lineTo(X(t), H - pad.b); ctx.stroke(); });
        ctx.setLineDash([]);
      }
      ctx.strokeStyle = "rgb(40,40,40)"; ctx.lineWidth = 1.5; ctx.beginPath();
      var pen = false;
      ap.forEach(function (v, i) {
        if (v === null) { pen = false; return; }
        if (pen) ctx.lineTo(X(timeOfFrame(i)), Y(v)); else ctx.moveTo(X(timeOfFrame(i)), Y(v));
        pen = true;
      });
      ctx.stroke();
      ctx.fillStyle = "rgb(31,119,180)"; ctx.font = "12px sans-serif";
      (data.taps || []).forEach(function (tp) {
        var i = frameAtTime(tp[peakKey]);
        var v = ap[i];
        if (v === null || v === undefined) return;
        ctx.beginPath(); ctx.arc(X(tp[peakKey]), Y(v), 3, 0, 2 * Math.PI); ctx.fill();
        ctx.fillText(String(tp.index + 1), X(tp[peakKey]) - 3, Y(v) - 6);
      });
      ctx.fillStyle = "rgb(60,60,60)";
      ctx.fillText(data.unit || "mm", 4, pad.t + 10);
      for (var s = 0; s <= duration; s += 1) ctx.fillText(s + " s", X(s) - 6, H - 8);
      for (var m = 0; m <= ymax; m += yStep) ctx.fillText(String(m), 8, Y(m) + 4);
      ctx.strokeStyle = "rgb(214,39,40)"; ctx.lineWidth = 2; ctx.beginPath();
      ctx.moveTo(X(cursor), pad.t); ctx.lineTo(X(cursor), H - pad.b); ctx.stroke();
      plot.setAttribute("data-cursor-s", cursor.toFixed(4));
      plot.setAttribute("data-cursor-x", X(cursor).toFixed(2));
    }
    if (plot) {
      plot.addEventListener("click", function (e) {
        var box = plot.getBoundingClientRect();
        var x = (e.clientX - box.left) * W / box.width;
        var t = (x - pad.l) / (W - pad.l - pad.r) * duration;
        var hit = (data.taps || []).concat(data.excluded_taps || [], data.outside_window_taps || []).filter(function (tp) {
          return t >= tp.t_start_s && t <= tp.t_end_s;
        })[0];
        seekFrame(frameAtTime(hit ? hit.t_start_s : t));
      });
      plot.addEventListener("keydown", function (e) {
        if (e.key === "ArrowLeft" || e.key === "ArrowRight") {
          e.preventDefault(); e.stopPropagation();
          seekFrame(current() + (e.key === "ArrowLeft" ? -1 : 1));
        }
      });
    }
    fit();
    drawPlot(0);
    window.addEventListener("resize", function () { fit(); drawPlot(lastCursor); });
    window.bradyscopeReview = { seekFrame: seekFrame, fps: fps, frameAtTime: frameAtTime };
  }

  document.addEventListener("DOMContentLoaded", function () {
    var block = document.getElementById("review-data");
    if (!block) return;
    setup(JSON.parse(block.textContent));
  });
})();
