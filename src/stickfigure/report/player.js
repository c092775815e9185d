/* stickfigure report: the skeleton player and the page's self-check.
 * Everything it needs is in the JSON block #report-data; it loads nothing else. */
(function () {
  "use strict";
  var root = document.documentElement;
  var errors = [];
  function recordError(msg) {
    errors.push(String(msg));
    root.setAttribute("data-errors", errors.join(" | "));
  }
  window.addEventListener("error", function (ev) {
    recordError(ev.message || (ev.target && ev.target.tagName ? "failed to load " + ev.target.tagName : "error"));
  }, true);

  var data;
  try {
    data = JSON.parse(document.getElementById("report-data").textContent);
  } catch (e) {
    recordError("report data unreadable: " + e);
    root.setAttribute("data-selfcheck", "fail");
    return;
  }

  function Player(el, d) {
    this.el = el;
    this.d = d;
    this.frame = 0;
    this.playing = false;
    this.speed = 1;
    this.drawn = 0;
    this.show = { video: true, points: true, sticks: true, joints: true, trails: false, labels: true, imputed: true,
                  zoom: !!d.focus };
    this.backgrounds = [];
    this.build();
  }

  Player.prototype.build = function () {
    var d = this.d, self = this;
    var canvas = document.createElement("canvas");
    canvas.setAttribute("tabindex", "0");
    canvas.setAttribute("aria-label", "skeleton animation; space plays or pauses, arrow keys step");
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.el.querySelector(".stage").appendChild(canvas);
    this.setView(!!d.focus);

    var c = this.el.querySelector(".controls");
    this.btn = c.querySelector("button.play");
    this.slider = c.querySelector("input.seek");
    this.label = c.querySelector(".frame");
    this.slider.max = String(d.n_frames - 1);
    this.btn.addEventListener("click", function () { self.toggle(); });
    c.querySelector("button.prev").addEventListener("click", function () { self.step(-1); });
    c.querySelector("button.next").addEventListener("click", function () { self.step(1); });
    this.slider.addEventListener("input", function () { self.pause(); self.seek(parseInt(self.slider.value, 10)); });
    c.querySelector("select.speed").addEventListener("change", function (ev) { self.speed = parseFloat(ev.target.value); });
    Array.prototype.forEach.call(this.el.querySelectorAll("input[data-layer]"), function (box) {
      var layer = box.getAttribute("data-layer");
      if (!(layer in self.show)) return;
      box.checked = self.show[layer];
      if (layer === "zoom" && !self.d.focus) { box.disabled = true; box.parentNode.style.display = "none"; }
      box.addEventListener("change", function () {
        self.show[layer] = box.checked;
        if (layer === "zoom") self.setView(box.checked);
        self.draw();
      });
    });
    canvas.addEventListener("keydown", function (ev) {
      if (ev.key === " ") { ev.preventDefault(); self.toggle(); }
      else if (ev.key === "ArrowRight") { ev.preventDefault(); self.pause(); self.step(1); }
      else if (ev.key === "ArrowLeft") { ev.preventDefault(); self.pause(); self.step(-1); }
    });
    var pending = [];
    (d.backgrounds || []).forEach(function (uri, i) {
      var img = new Image();
      self.backgrounds[i] = img;
      pending.push(new Promise(function (resolve) {
        img.onload = function () { resolve(true); if (i === self.bgIndex(self.frame)) self.draw(); };
        img.onerror = function () { recordError("video frame " + i + " could not be decoded"); resolve(false); };
      }));
      img.src = uri;
    });
    this.ready = Promise.all(pending);
    this.draw();
  };

  /* The part of the picture shown: the whole frame, or (zoom) the box around the figure. */
  Player.prototype.setView = function (zoom) {
    var d = this.d;
    var v = zoom && d.focus ? d.focus : (d.pixels ? [0, 0, d.width, d.height] : [d.xmin, d.ymax - d.height, d.width, d.height]);
    this.view = v;
    var s = d.pixels ? Math.min(zoom ? 3 : 1.5, 960 / v[2], 720 / v[3]) : Math.min(960 / v[2], 560 / v[3]);
    this.scale = s;
    this.pad = d.pixels ? 0 : 16;
    this.canvas.width = Math.round(v[2] * s) + 2 * this.pad;
    this.canvas.height = Math.round(v[3] * s) + 2 * this.pad;
  };

  Player.prototype.bgIndex = function (f) {
    var idx = this.d.background_index;
    return idx ? idx[f] : -1;
  };

  Player.prototype.toCanvas = function (x, y) {
    var d = this.d, s = this.scale, p = this.pad, v = this.view;
    if (d.pixels) return [(x - v[0]) * s, (y - v[1]) * s];
    return [(x - v[0]) * s + p, (v[1] + v[3] - y) * s + p];
  };

  Player.prototype.draw = function () {
    var d = this.d, ctx = this.ctx, f = this.frame, self = this;
    var W = this.canvas.width, H = this.canvas.height;
    ctx.fillStyle = d.pixels ? "#0b0d12" : "#ffffff";
    ctx.fillRect(0, 0, W, H);
    var bi = this.bgIndex(f);
    var img = bi >= 0 ? this.backgrounds[bi] : null;
    if (this.show.video && img && img.complete && img.naturalWidth > 0) {
      var k = img.naturalWidth / d.width, v = this.view;  // frames are stored downscaled
      ctx.drawImage(img, v[0] * k, v[1] * k, v[2] * k, v[3] * k, 0, 0, W, H);
    } else if (!d.pixels) {
      this.grid();
    }
    var lw = Math.max(2, Math.min(W, H) / 110);
    var pr = Math.max(3, Math.min(W, H) / 130);
    var pts = d.points[f], imp = d.imputed ? d.imputed[f] : null;
    var P = d.labels.length;
    function colour(p) { var l = d.labels[p]; return l >= 0 ? d.colors[l] : d.unassigned; }

    if (this.show.trails) {
      ctx.lineWidth = 1;
      for (var p = 0; p < P; p++) {
        ctx.strokeStyle = colour(p);
        ctx.globalAlpha = 0.6;
        ctx.beginPath();
        var started = false;
        for (var g = Math.max(0, f - 12); g <= f; g++) {
          var q = d.points[g];
          if (q[2 * p] === null) { started = false; continue; }
          var c = this.toCanvas(q[2 * p], q[2 * p + 1]);
          if (started) ctx.lineTo(c[0], c[1]); else ctx.moveTo(c[0], c[1]);
          started = true;
        }
        ctx.stroke();
      }
      ctx.globalAlpha = 1;
    }
    if (this.show.sticks) {
      d.segments.forEach(function (seg) {
        var e = seg.xy[f];
        if (!e) return;
        var a = self.toCanvas(e[0], e[1]), b = self.toCanvas(e[2], e[3]);
        ctx.lineCap = "round";
        ctx.strokeStyle = "rgba(0,0,0,0.75)";
        ctx.lineWidth = lw + 3;
        ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke();
        ctx.strokeStyle = d.colors[seg.stick];
        ctx.lineWidth = lw;
        ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke();
      });
    }
    if (this.show.points) {
      for (var i = 0; i < P; i++) {
        var x = pts[2 * i], y = pts[2 * i + 1], hollow = false;
        if (x === null) {
          if (!this.show.imputed || !imp || imp[2 * i] === null) continue;
          x = imp[2 * i]; y = imp[2 * i + 1]; hollow = true;
        }
        var cc = this.toCanvas(x, y);
        ctx.beginPath();
        ctx.arc(cc[0], cc[1], pr, 0, 2 * Math.PI);
        if (hollow) {
          ctx.lineWidth = 1.5; ctx.strokeStyle = colour(i); ctx.stroke();
        } else {
          ctx.fillStyle = colour(i); ctx.fill();
          ctx.lineWidth = 0.6; ctx.strokeStyle = "rgba(0,0,0,0.5)"; ctx.stroke();
        }
      }
    }
    if (this.show.joints) {
      d.joints.forEach(function (jt) {
        var j = jt[f];
        if (!j) return;
        var c = self.toCanvas(j[0], j[1]);
        ctx.beginPath();
        ctx.arc(c[0], c[1], pr * 1.8, 0, 2 * Math.PI);
        ctx.fillStyle = "#ffffff"; ctx.fill();
        ctx.lineWidth = 2; ctx.strokeStyle = "#111111"; ctx.stroke();
      });
    }
    if (this.show.labels) {
      ctx.font = "600 " + Math.max(11, Math.round(lw * 3.2)) + "px system-ui, sans-serif";
      ctx.textBaseline = "middle";
      d.stick_names.forEach(function (name, s) {
        var c0 = d.stick_label_xy[s][f];
        if (!c0) return;
        var c = self.toCanvas(c0[0], c0[1]);
        ctx.lineWidth = 3; ctx.strokeStyle = "rgba(0,0,0,0.8)"; ctx.strokeText(name, c[0] + 6, c[1]);
        ctx.fillStyle = d.colors[s]; ctx.fillText(name, c[0] + 6, c[1]);
      });
    }
    this.slider.value = String(f);
    var abs = d.frame_numbers ? d.frame_numbers[f] : f;
    this.label.textContent = "frame " + abs + " (" + (f + 1) + "/" + d.n_frames + ")";
    this.drawn += 1;
  };

  Player.prototype.grid = function () {
    var ctx = this.ctx, W = this.canvas.width, H = this.canvas.height;
    ctx.strokeStyle = "#eef0f4"; ctx.lineWidth = 1;
    for (var x = 0; x < W; x += 40) { ctx.beginPath(); ctx.moveTo(x + 0.5, 0); ctx.lineTo(x + 0.5, H); ctx.stroke(); }
    for (var y = 0; y < H; y += 40) { ctx.beginPath(); ctx.moveTo(0, y + 0.5); ctx.lineTo(W, y + 0.5); ctx.stroke(); }
  };

  Player.prototype.seek = function (f) {
    var n = this.d.n_frames;
    this.frame = ((f % n) + n) % n;
    this.draw();
  };
  Player.prototype.step = function (k) { this.seek(this.frame + k); };
  Player.prototype.pause = function () { this.playing = false; this.btn.textContent = "Play"; };
  Player.prototype.toggle = function () {
    if (this.playing) { this.pause(); return; }
    this.playing = true;
    this.btn.textContent = "Pause";
    var self = this, last = null, acc = 0, fps = this.d.fps || 25;
    function tick(t) {
      if (!self.playing) return;
      if (last !== null) acc += (t - last) / 1000 * fps * self.speed;
      last = t;
      if (acc >= 1) { var k = Math.floor(acc); acc -= k; self.step(k); }
      window.requestAnimationFrame(tick);
    }
    window.requestAnimationFrame(tick);
  };

  var players = [];
  try {
    Array.prototype.forEach.call(document.querySelectorAll(".player[data-player]"), function (el) {
      var d = data.players[el.getAttribute("data-player")];
      if (d) players.push(new Player(el, d));
    });
  } catch (e) {
    recordError("player failed: " + e);
  }

  /* Self-check: every image decoded and every player drawn with its video frames. */
  function imagesDecoded() {
    var imgs = Array.prototype.slice.call(document.images);
    return Promise.all(imgs.map(function (img) {
      return (img.decode ? img.decode() : Promise.resolve()).then(function () {
        return img.naturalWidth > 0;
      }, function () { return false; });
    }));
  }
  window.addEventListener("load", function () {
    Promise.all([imagesDecoded()].concat(players.map(function (p) { return p.ready; }))).then(function (res) {
      var imgs = res[0], bad = imgs.filter(function (ok) { return !ok; }).length;
      var frames = res.slice(1).reduce(function (n, r) { return n + r.filter(Boolean).length; }, 0);
      var drawn = players.every(function (p) { return p.drawn > 0; });
      if (bad) recordError(bad + " image(s) not decoded");
      if (!drawn) recordError("a player did not draw");
      root.setAttribute("data-images", String(imgs.length - bad));
      root.setAttribute("data-video-frames", String(frames));
      root.setAttribute("data-players", String(players.length));
      root.setAttribute("data-selfcheck", errors.length ? "fail" : "ok");
    });
  });
})();
