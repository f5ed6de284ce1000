// bradyscope capture station, the parts without a page: the live quality gate's image
// analysis, the frame timestamps of a recorded WebM file, and their pairing with each
// frame's capture time. Plain JavaScript, no library; docs/capture.md describes the rules.
"use strict";

(function (root) {
  // A marker is a small round spot, nearly white under the ring light, well above its
  // surroundings (docs/capture.md, "The quality gate").
  var MARKER_PEAK = 200; // gray level its brightest pixel reaches at least
  var MARKER_CONTRAST = 80; // gray levels above the mean of a ring around it
  var MARKER_MIN_AREA = 3; // px of the analysed image above the spot threshold
  var MARKER_DIAMETER_PX = [2, 60]; // px of the full image
  var MAX_ELONGATION = 4; // major / minor axis: a streak of motion blur passes, a line does not
  var MIN_FILL = 0.5; // area / area of the moment ellipse: ragged or hollow shapes fail
  var SATURATED = 250; // gray level counted as white

  /** Gray levels (Rec. 601 luma, 0-255) of an RGBA pixel array. */
  function lumaOf(rgba, count) {
    var out = new Uint8Array(count);
    for (var i = 0, j = 0; i < count; i += 1, j += 4) {
      out[i] = (77 * rgba[j] + 150 * rgba[j + 1] + 29 * rgba[j + 2]) >> 8;
    }
    return out;
  }

  function median(values) {
    if (!values.length) return NaN;
    var s = Array.prototype.slice.call(values).sort(function (a, b) { return a - b; });
    var h = s.length >> 1;
    return s.length % 2 ? s[h] : 0.5 * (s[h - 1] + s[h]);
  }

  /** Mean gray level of the border of the box [x0, x1] x [y0, y1] (clipped to the image). */
  function ringMean(luma, width, height, x0, y0, x1, y1) {
    x0 = Math.max(0, x0); y0 = Math.max(0, y0);
    x1 = Math.min(width - 1, x1); y1 = Math.min(height - 1, y1);
    var sum = 0, n = 0, x, y;
    for (x = x0; x <= x1; x += 1) {
      sum += luma[y0 * width + x] + luma[y1 * width + x]; n += 2;
    }
    for (y = y0 + 1; y < y1; y += 1) {
      sum += luma[y * width + x0] + luma[y * width + x1]; n += 2;
    }
    return n ? sum / n : 0;
  }

  /**
   * The quality gate's look at one (downscaled) frame.
   *
   * luma: Uint8Array (width * height) gray levels; scale: analysed px per full-image px (<= 1).
   * Returns {markers, clipped, saturated, spots}: marker-like spots inside the image and
   * touching its border, the share of white pixels (0-1), and the spots' centres and
   * diameters in full-image px.
   */
  function analyseLuma(luma, width, height, scale) {
    var n = width * height;
    var hist = new Uint32Array(256);
    for (var i = 0; i < n; i += 1) hist[luma[i]] += 1;
    var white = 0, half = n / 2, seen = 0, level = 0;
    for (var v = SATURATED; v < 256; v += 1) white += hist[v];
    for (level = 0; level < 256; level += 1) { seen += hist[level]; if (seen >= half) break; }
    // Spot pixels: at least mid-gray and well above the typical (median) pixel.
    var low = Math.max(128, level + 40);
    var maxArea = Math.PI / 4 * Math.pow(MARKER_DIAMETER_PX[1] * scale * MAX_ELONGATION, 2);
    var labels = new Uint8Array(n); // 1 = visited
    var stack = new Int32Array(n);
    var result = { markers: 0, clipped: 0, saturated: n ? white / n : 0, spots: [] };
    for (var start = 0; start < n; start += 1) {
      if (labels[start] || luma[start] < low) continue;
      var top = 0, area = 0, peak = 0, sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
      var minX = width, maxX = -1, minY = height, maxY = -1;
      labels[start] = 1; stack[top++] = start;
      while (top > 0) {
        var p = stack[--top], x = p % width, y = (p - x) / width, g = luma[p];
        area += 1; if (g > peak) peak = g;
        sx += x; sy += y; sxx += x * x; syy += y * y; sxy += x * y;
        if (x < minX) minX = x; if (x > maxX) maxX = x; if (y < minY) minY = y; if (y > maxY) maxY = y;
        if (x > 0 && !labels[p - 1] && luma[p - 1] >= low) { labels[p - 1] = 1; stack[top++] = p - 1; }
        if (x < width - 1 && !labels[p + 1] && luma[p + 1] >= low) { labels[p + 1] = 1; stack[top++] = p + 1; }
        if (y > 0 && !labels[p - width] && luma[p - width] >= low) { labels[p - width] = 1; stack[top++] = p - width; }
        if (y < height - 1 && !labels[p + width] && luma[p + width] >= low) { labels[p + width] = 1; stack[top++] = p + width; }
      }
      if (peak < MARKER_PEAK || area < MARKER_MIN_AREA || area > maxArea) continue;
      var pad = Math.max(2, Math.round(0.5 * Math.max(maxX - minX, maxY - minY)) + 1);
      var ring = ringMean(luma, width, height, minX - pad, minY - pad, maxX + pad, maxY + pad);
      if (peak - ring < MARKER_CONTRAST) continue;
      var mx = sx / area, my = sy / area;
      var cxx = sxx / area - mx * mx + 1 / 12, cyy = syy / area - my * my + 1 / 12;
      var cxy = sxy / area - mx * my;
      var tr = cxx + cyy, det = cxx * cyy - cxy * cxy;
      var disc = Math.sqrt(Math.max(0, tr * tr / 4 - det));
      var major = 4 * Math.sqrt(tr / 2 + disc), minor = 4 * Math.sqrt(Math.max(1e-9, tr / 2 - disc));
      var diameter = minor / scale;
      var touches = minX === 0 || minY === 0 || maxX === width - 1 || maxY === height - 1;
      if (touches) { result.clipped += 1; continue; } // cut by the border: shape unknown
      if (major / minor > MAX_ELONGATION || area / (Math.PI / 4 * major * minor) < MIN_FILL) continue;
      if (diameter < MARKER_DIAMETER_PX[0] || diameter > MARKER_DIAMETER_PX[1]) continue;
      result.markers += 1;
      result.spots.push({ x: mx / scale, y: my / scale, diameter_px: diameter });
    }
    return result;
  }

  // -- WebM: each frame's timestamp as the recorder wrote it (ms) --------------------------

  function readVint(bytes, pos, keepMarker) {
    var first = bytes[pos];
    if (first === undefined || first === 0) return null;
    var length = 1, mask = 0x80;
    while (!(first & mask)) { mask >>= 1; length += 1; }
    if (pos + length > bytes.length) return null;
    var value = keepMarker ? first : first & (mask - 1), allOnes = (first & (mask - 1)) === mask - 1;
    for (var i = 1; i < length; i += 1) {
      value = value * 256 + bytes[pos + i];
      if (bytes[pos + i] !== 0xff) allOnes = false;
    }
    return { value: value, length: length, unknown: !keepMarker && allOnes };
  }

  function readUint(bytes, pos, size) {
    var value = 0;
    for (var i = 0; i < size; i += 1) value = value * 256 + bytes[pos + i];
    return value;
  }

  var MASTER = { 0x18538067: 1, 0x1f43b675: 1, 0xa0: 1, 0x1654ae6b: 1, 0xae: 1, 0x1549a966: 1 };
  var TRACK_ENTRY = 0xae, TRACK_NUMBER = 0xd7, TRACK_TYPE = 0x83, TIMECODE_SCALE = 0x2ad7b1;
  var CLUSTER_TIMECODE = 0xe7, SIMPLE_BLOCK = 0xa3, BLOCK = 0xa1;

  /**
   * The presentation time (ms) of every frame of the video track of a WebM file, in file
   * order (what a decoder counts). Null if the bytes are not a WebM file.
   */
  function webmFrameTimesMs(buffer) {
    var b = new Uint8Array(buffer), pos = 0, scaleNs = 1e6, cluster = 0;
    var video = null, number = null, type = null, out = [];
    if (readUint(b, 0, 4) !== 0x1a45dfa3) return null;
    while (pos < b.length) {
      var id = readVint(b, pos, true);
      if (!id) break;
      var size = readVint(b, pos + id.length, false);
      if (!size) break;
      pos += id.length + size.length;
      if (MASTER[id.value]) { // descend: its children follow
        if (id.value === TRACK_ENTRY) { number = null; type = null; }
        continue;
      }
      if (size.unknown || pos + size.value > b.length) break; // a leaf cut off: the end
      var body = pos;
      pos += size.value;
      if (id.value === TIMECODE_SCALE) scaleNs = readUint(b, body, size.value);
      else if (id.value === TRACK_NUMBER) number = readUint(b, body, size.value);
      else if (id.value === TRACK_TYPE) type = readUint(b, body, size.value);
      else if (id.value === CLUSTER_TIMECODE) cluster = readUint(b, body, size.value);
      else if (id.value === SIMPLE_BLOCK || id.value === BLOCK) {
        var track = readVint(b, body, false);
        if (!track) continue;
        var rel = (b[body + track.length] << 8) | b[body + track.length + 1];
        if (rel & 0x8000) rel -= 0x10000;
        if (video === null || track.value === video) out.push((cluster + rel) * scaleNs / 1e6);
      }
      if (video === null && number !== null && type === 1) video = number;
    }
    return out;
  }

  // -- pairing the recorded frames with their capture times ---------------------------------

  function pairUp(containerMs, mediaMs, offsetMs, tolMs) {
    var j = 0, pairs = new Int32Array(containerMs.length).fill(-1), count = 0, misfit = 0;
    for (var k = 0; k < containerMs.length; k += 1) {
      var target = containerMs[k] + offsetMs;
      while (j < mediaMs.length && mediaMs[j] < target - tolMs) j += 1;
      if (j < mediaMs.length && Math.abs(mediaMs[j] - target) <= tolMs) {
        pairs[k] = j; count += 1; misfit += Math.abs(mediaMs[j] - target); j += 1;
      }
    }
    return { pairs: pairs, count: count, misfit: misfit };
  }

  /**
   * The capture time (s, the camera's clock) of every recorded frame.
   *
   * containerMs: the frames' timestamps in the file (ms, from the first frame, rounded by
   * the recorder); mediaTimesS: the capture times seen by requestVideoFrameCallback during
   * the recording (s; a frame the page did not show has none). Each recorded frame is
   * paired with the capture time whose distance to it, after the best common offset, is
   * within 0.3 frame interval; an unpaired frame keeps its file time moved by that offset.
   * Returns {times_s, paired} or null when fewer than half the frames could be paired.
   */
  function alignFrameTimes(containerMs, mediaTimesS) {
    var n = containerMs.length;
    var media = [];
    for (var i = 0; i < mediaTimesS.length; i += 1) {
      var t = 1000 * mediaTimesS[i];
      if (isFinite(t) && (!media.length || t > media[media.length - 1])) media.push(t);
    }
    if (n < 2 || media.length < 2) return null;
    var steps = [];
    for (var k = 1; k < n; k += 1) steps.push(containerMs[k] - containerMs[k - 1]);
    var interval = median(steps);
    if (!(interval > 0)) return null;
    var tol = 0.3 * interval, best = null;
    for (var a = 0; a < Math.min(12, media.length); a += 1) {
      for (var c = 0; c < Math.min(12, n); c += 1) {
        var trial = pairUp(containerMs, media, media[a] - containerMs[c], tol);
        trial.offset = media[a] - containerMs[c];
        if (!best || trial.count > best.count || (trial.count === best.count && trial.misfit < best.misfit)) best = trial;
      }
    }
    var residuals = [];
    for (k = 0; k < n; k += 1) if (best.pairs[k] >= 0) residuals.push(media[best.pairs[k]] - containerMs[k] - best.offset);
    var offset = best.offset + median(residuals);
    var final = pairUp(containerMs, media, offset, tol);
    if (final.count < 0.5 * n) return null;
    var times = new Float64Array(n);
    for (k = 0; k < n; k += 1) {
      if (final.pairs[k] >= 0) { times[k] = media[final.pairs[k]]; continue; }
      // Unpaired: the file's time, kept between its paired neighbours (the file's times
      // are rounded to 1 ms and were taken a little later than the capture).
      var next = k + 1;
      while (next < n && final.pairs[next] < 0) next += 1;
      var lo = k > 0 ? times[k - 1] : -Infinity;
      var hi = next < n ? media[final.pairs[next]] : Infinity;
      var t = containerMs[k] + offset;
      if (!(t > lo && t < hi)) t = isFinite(hi) && isFinite(lo) ? lo + (hi - lo) / (next - k + 1) : (isFinite(lo) ? lo + interval : hi - interval * (next - k));
      times[k] = t;
    }
    for (k = 0; k < n; k += 1) {
      times[k] /= 1000;
      if (k > 0 && !(times[k] > times[k - 1])) return null;
    }
    return { times_s: times, paired: final.count };
  }

  /** A timestamps file (INTERFACES.md: frame,time_s). */
  function timesCsv(times) {
    var lines = ["frame,time_s"];
    for (var k = 0; k < times.length; k += 1) lines.push(k + "," + times[k].toFixed(6));
    return lines.join("\n") + "\n";
  }

  /** Frames, length (s), rate (Hz) and frames lost (gaps of 1.5 intervals or more) of one
   * camera's take from its frame times (s), and its longest stretch without frames: ``gap``
   * {start_s, end_s} from the first frame. */
  function takeFacts(times) {
    var n = times.length;
    if (n < 2) return { frame_count: n, duration_s: 0, fps: 0, dropped_frames: 0, gap: null };
    var steps = [];
    for (var k = 1; k < n; k += 1) steps.push(times[k] - times[k - 1]);
    var interval = median(steps), lost = 0, longest = 0;
    for (k = 0; k < steps.length; k += 1) {
      if (steps[k] >= 1.5 * interval) lost += Math.max(1, Math.round(steps[k] / interval) - 1);
      if (steps[k] > steps[longest]) longest = k;
    }
    return {
      frame_count: n, duration_s: times[n - 1] - times[0] + interval, fps: 1 / interval, dropped_frames: lost,
      gap: { start_s: times[longest] - times[0], end_s: times[longest + 1] - times[0] },
    };
  }

  /** The sentence refusing a take whose camera delivered no frames for longer than
   * ``holeS`` and ``holeFrames`` intervals (the server's rule, core.video.HOLE_S), or null. */
  function holeSentence(side, facts, holeS, holeFrames) {
    if (!facts || !facts.gap || !(facts.fps > 0)) return null;
    var gap = facts.gap, interval = 1 / facts.fps, length = gap.end_s - gap.start_s;
    if (!(length > Math.max(holeS, holeFrames * interval))) return null;
    return "The " + side + " camera's recording has no frames between " + gap.start_s.toFixed(2) + " s and "
      + gap.end_s.toFixed(2) + " s (about " + (Math.round(length / interval) - 1) + " frames missing at its "
      + facts.fps.toFixed(0) + " frames per second): the camera delivered no frames for that long (a computer"
      + " too busy to take them, or a camera that paused). The take was not sent and nothing was stored;"
      + " record it again.";
  }

  /**
   * How long a camera did not see every marker, from the gate's looks while recording.
   *
   * samples: [{t_s, markers}] in time order (s from the start of the take); expected: the
   * task's markers; endS: the take's length so far (s). Each look stands for the time until
   * the next one. Returns {missing_s, longest: {start_s, end_s} or null, current_s}: the
   * time without every marker, its longest stretch, and how long it has lasted up to
   * ``endS`` if it still does (else 0).
   */
  function markerGaps(samples, expected, endS) {
    var missing = 0, longest = null, start = null;
    for (var i = 0; i < samples.length; i += 1) {
      var t = samples[i].t_s, next = i + 1 < samples.length ? samples[i + 1].t_s : Math.max(t, endS);
      if (samples[i].markers < expected) {
        missing += next - t;
        if (start === null) start = t;
        if (!longest || next - start > longest.end_s - longest.start_s) longest = { start_s: start, end_s: next };
      } else {
        start = null;
      }
    }
    return { missing_s: missing, longest: longest, current_s: start === null ? 0 : Math.max(0, endS - start) };
  }

  root.BradyscopeCapture = {
    lumaOf: lumaOf,
    analyseLuma: analyseLuma,
    webmFrameTimesMs: webmFrameTimesMs,
    alignFrameTimes: alignFrameTimes,
    timesCsv: timesCsv,
    takeFacts: takeFacts,
    holeSentence: holeSentence,
    markerGaps: markerGaps,
    median: median,
  };
})(typeof window !== "undefined" ? window : globalThis);
