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

  // -- the rig's geometry: are the cameras swapped? ----------------------------------------

  /** Undistorted normalized coordinates of pixel (x, y) (OpenCV's model: k1, k2, p1, p2, k3
   * and the rational k4-k6, solved by fixed-point iteration as cv2.undistortPoints does). */
  function normalize(cam, x, y) {
    var K = cam.K, d = cam.dist;
    var y0 = (y - K[1][2]) / K[1][1];
    var x0 = (x - K[0][2] - K[0][1] * y0) / K[0][0];
    var k = function (i) { return d[i] || 0; };
    var xn = x0, yn = y0;
    for (var it = 0; it < 20; it += 1) {
      var r2 = xn * xn + yn * yn;
      var icdist = (1 + ((k(7) * r2 + k(6)) * r2 + k(5)) * r2) / (1 + ((k(4) * r2 + k(1)) * r2 + k(0)) * r2);
      var dx = 2 * k(2) * xn * yn + k(3) * (r2 + 2 * xn * xn);
      var dy = k(2) * (r2 + 2 * yn * yn) + 2 * k(3) * xn * yn;
      xn = (x0 - dx) * icdist; yn = (y0 - dy) * icdist;
    }
    return [xn, yn, 1];
  }

  function mulT(A, B) { // A B^T, 3 x 3
    var out = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
    for (var i = 0; i < 3; i += 1) for (var j = 0; j < 3; j += 1) {
      out[i][j] = A[i][0] * B[j][0] + A[i][1] * B[j][1] + A[i][2] * B[j][2];
    }
    return out;
  }
  function apply(A, v) { return [0, 1, 2].map(function (i) { return A[i][0] * v[0] + A[i][1] * v[1] + A[i][2] * v[2]; }); }
  function applyT(A, v) { return [0, 1, 2].map(function (i) { return A[0][i] * v[0] + A[1][i] * v[1] + A[2][i] * v[2]; }); }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

  /** The right camera's pose relative to the left one's, the essential matrix, and the
   * right camera's centre in the left camera's frame (mm). Null if the geometry is unusable
   * (a distortion model other than OpenCV's 4, 5 or 8 coefficients). */
  function stereoOf(geometry) {
    var l = geometry && geometry.left, r = geometry && geometry.right;
    if (!l || !r || [l, r].some(function (c) { return [4, 5, 8].indexOf(c.dist.length) < 0; })) return null;
    var R = mulT(r.R, l.R); // R_right_from_left = R_r R_l^T
    var Rt = apply(R, l.t);
    var t = [r.t[0] - Rt[0], r.t[1] - Rt[1], r.t[2] - Rt[2]];
    var tx = [[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]];
    var E = [0, 1, 2].map(function (i) { return [0, 1, 2].map(function (j) { return tx[i][0] * R[0][j] + tx[i][1] * R[1][j] + tx[i][2] * R[2][j]; }); });
    var c = applyT(R, t);
    return { left: l, right: r, R: R, E: E, centre: [-c[0], -c[1], -c[2]], focal: (l.K[0][0] + r.K[0][0]) / 2 };
  }

  /** How far (px) a left and a right view of one point are from fitting the rig: the
   * Sampson distance to the epipolar constraint, Infinity when the two rays meet behind
   * either camera. xl, xr: normalized coordinates. */
  function pairMisfitPx(stereo, xl, xr) {
    var El = apply(stereo.E, xl), Er = applyT(stereo.E, xr);
    var den = El[0] * El[0] + El[1] * El[1] + Er[0] * Er[0] + Er[1] * Er[1];
    var sampson = den > 0 ? Math.abs(dot(xr, El)) / Math.sqrt(den) : Infinity;
    // Closest points of the rays: left lam * xl, right centre + mu * R^T xr (left frame).
    var b = applyT(stereo.R, xr), c = stereo.centre;
    var aa = dot(xl, xl), ab = dot(xl, b), bb = dot(b, b), ac = dot(xl, c), bc = dot(b, c);
    var det = ab * ab - aa * bb;
    if (Math.abs(det) < 1e-12) return Infinity; // parallel rays: no depth
    var lam = (ab * bc - bb * ac) / det, mu = (aa * bc - ab * ac) / det;
    return lam > 0 && mu > 0 ? sampson * stereo.focal : Infinity;
  }

  function permutations(n) {
    if (n <= 1) return [[0].slice(0, n)];
    var out = [];
    permutations(n - 1).forEach(function (p) {
      for (var i = 0; i <= p.length; i += 1) out.push(p.slice(0, i).concat([n - 1], p.slice(i)));
    });
    return out;
  }

  /** The worst pair's misfit (px) under the best pairing of the left spots with the right
   * spots, read with the rig's left camera looking at ``leftSpots``. */
  function viewsMisfitPx(stereo, leftSpots, rightSpots) {
    var xl = leftSpots.map(function (s) { return normalize(stereo.left, s.x, s.y); });
    var xr = rightSpots.map(function (s) { return normalize(stereo.right, s.x, s.y); });
    var best = Infinity;
    permutations(xl.length).forEach(function (perm) {
      var worst = 0;
      for (var i = 0; i < perm.length && worst < best; i += 1) worst = Math.max(worst, pairMisfitPx(stereo, xl[i], xr[perm[i]]));
      if (worst < best) best = worst;
    });
    return best;
  }

  /**
   * The evidence of one look at both views on the cameras' order: how far (px) the spots
   * are from fitting the rig's geometry as the cameras are chosen and with the two exchanged.
   *
   * geometry: {left, right} with each camera's K (3 x 3), dist, R and t (the rig's
   * calibration, R_cam_from_world, t_cam_from_world_mm); leftSpots, rightSpots: the spots
   * ({x, y}, full-image px) the gate found in the views chosen as left and right. Null
   * without 1 to 3 spots in each view, as many in both.
   */
  function swapEvidence(geometry, leftSpots, rightSpots) {
    var stereo = stereoOf(geometry);
    var n = leftSpots.length;
    if (!stereo || n < 1 || n > 3 || rightSpots.length !== n) return null;
    return {
      chosen_px: viewsMisfitPx(stereo, leftSpots, rightSpots),
      swapped_px: viewsMisfitPx(stereo, rightSpots, leftSpots),
    };
  }

  root.BradyscopeCapture = {
    lumaOf: lumaOf,
    analyseLuma: analyseLuma,
    webmFrameTimesMs: webmFrameTimesMs,
    alignFrameTimes: alignFrameTimes,
    timesCsv: timesCsv,
    takeFacts: takeFacts,
    holeSentence: holeSentence,
    swapEvidence: swapEvidence,
    markerGaps: markerGaps,
    median: median,
  };
})(typeof window !== "undefined" ? window : globalThis);
