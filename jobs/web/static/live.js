// Live parts of the dashboard: a job's targets and a drip-feed's line by Server-Sent
// Events, and a confirmation before destructive forms. No framework, nothing downloaded.
"use strict";

function text(el, value) { if (el) el.textContent = value; }

function stateBadge(state) {
  const span = document.createElement("span");
  span.className = "state s-" + state;
  span.textContent = state;
  return span;
}

// The server ends a stream whose session has expired or was signed out: reloading the
// page shows the sign-in, and after it the page again.
function reloadWhenSignedOut(source) {
  source.addEventListener("signedout", () => { source.close(); window.location.reload(); });
}

function followJob(root) {
  const source = new EventSource(root.dataset.events);
  reloadWhenSignedOut(source);
  source.onmessage = (event) => {
    const job = JSON.parse(event.data);
    const badge = root.querySelector("[data-job-state]");
    if (badge) badge.replaceChildren(stateBadge(job.state));
    for (const [state, n] of Object.entries(job.counts)) {
      text(root.querySelector(`[data-count="${state}"]`), n);
    }
    const done = Object.entries(job.counts)
      .filter(([s]) => ["succeeded", "skipped", "failed", "cancelled"].includes(s))
      .reduce((sum, [, n]) => sum + n, 0);
    const bar = root.querySelector("[data-bar]");
    if (bar && job.total) bar.style.width = `${Math.round(100 * done / job.total)}%`;
    text(root.querySelector("[data-done]"), `${done} of ${job.total} final`);
    for (const t of job.targets) {
      const card = root.querySelector(`[data-target="${t.position}"]`);
      if (!card) continue;
      card.className = "target s-" + t.state;
      card.querySelector("[data-t-state]").replaceChildren(stateBadge(t.state));
      text(card.querySelector("[data-t-msg]"), t.errorCode ?
        `${t.errorCode} ${t.errorMsg}` + (t.statusMsg ? ` (${t.statusMsg})` : "") :
        (t.statusMsg || ""));
      text(card.querySelector("[data-t-attempts]"), t.attempts);
    }
    const retry = root.querySelector("[data-retry]");
    if (retry) retry.hidden = !((job.counts.failed || 0) + (job.counts.cancelled || 0));
  };
  source.addEventListener("end", () => {
    source.close();
    text(root.querySelector("[data-live]"), "finished");
    const cancel = root.querySelector("[data-cancel]");
    if (cancel) cancel.hidden = true;
  });
}

function followRun(root) {
  const source = new EventSource(root.dataset.events);
  reloadWhenSignedOut(source);
  source.onmessage = (event) => {
    const run = JSON.parse(event.data);
    text(root.querySelector("[data-line]"), run.line ?? "—");
    text(root.querySelector("[data-total]"), run.linesTotal ?? "—");
    text(root.querySelector("[data-rate]"), run.rate === null ? "—" : `${run.rate} blocks/s`);
    text(root.querySelector("[data-message]"), run.message || "");
    const badge = root.querySelector("[data-run-state]");
    if (badge) badge.replaceChildren(stateBadge(run.state));
    const bar = root.querySelector("[data-bar]");
    if (bar && run.linesTotal) bar.style.width = `${Math.round(100 * run.line / run.linesTotal)}%`;
    const stop = root.querySelector("[data-stop]");
    if (stop && !["queued", "running"].includes(run.state)) stop.hidden = true;
  };
  source.addEventListener("end", () => {
    source.close();
    text(root.querySelector("[data-live]"), "ended");
  });
}

document.addEventListener("DOMContentLoaded", () => {
  document.querySelectorAll("[data-follow-job]").forEach(followJob);
  document.querySelectorAll("[data-follow-run]").forEach(followRun);
  document.querySelectorAll("[data-refresh-s]").forEach(refreshWhenIdle);
  document.querySelectorAll("form[data-confirm]").forEach((form) => {
    form.addEventListener("submit", (event) => {
      if (!window.confirm(form.dataset.confirm)) event.preventDefault();
    });
  });
  // A form goes once: a second click while its answer loads sends nothing (the server
  // refuses a starting form's second sending too, jobs/web/once.py).
  document.querySelectorAll("form[method=post]").forEach((form) => {
    form.addEventListener("submit", (event) => {
      if (event.defaultPrevented) return;
      if (form.dataset.sending) event.preventDefault();
      else form.dataset.sending = "1";
    });
  });
});

// A wall display stays fresh: the page reloads itself every few seconds, but not under
// someone typing or choosing in it (what they had half done would be lost).
function refreshWhenIdle(marker) {
  const every = 1000 * Number(marker.dataset.refreshS);
  const busy = () => {
    const active = document.activeElement;
    if (active && ["INPUT", "SELECT", "TEXTAREA"].includes(active.tagName)) return true;
    const changed = (s) => {  // a select's first option is chosen when none is marked
      const initial = [...s.options].find((o) => o.defaultSelected) || s.options[0];
      return s.value !== (initial ? initial.value : "");
    };
    return [...document.querySelectorAll("input")].some((i) => i.value !== i.defaultValue) ||
      [...document.querySelectorAll("select")].some(changed);
  };
  setInterval(() => { if (!busy()) window.location.reload(); }, every);
}

// A page shown again from the browser's memory (Back) is asked for again: after a sign-out
// it must not show what the signed-in user saw, and what it shows may be long out of date.
window.addEventListener("pageshow", (event) => {
  if (event.persisted) window.location.reload();
});
