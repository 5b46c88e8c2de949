// pulsetrack console: the login form. POSTs user and password to /api/login (form-encoded);
// the server sets the HttpOnly session cookie, then we go to the console. A separate file
// because the server's Content-Security-Policy allows scripts from the origin only; it serves
// this file, /login.html, /style.css and /vendor/* before login.
"use strict";
(() => {
  const form = document.getElementById("login-form");
  const user = document.getElementById("user");
  const password = document.getElementById("password");
  const button = document.getElementById("login-button");
  const msg = document.getElementById("login-message");

  function show(kind, text) {
    msg.dataset.kind = kind;
    msg.textContent = text;
  }

  async function errorText(response) {
    try {
      const body = await response.json();
      if (body && typeof body.error === "string" && body.error) return body.error;
    } catch (_) { /* not JSON: fall through */ }
    return "";
  }

  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    if (!user.value || !password.value) {
      show("error", "enter a user and a password");
      (user.value ? password : user).focus();
      return;
    }
    const body = new URLSearchParams({ user: user.value, password: password.value }).toString();
    button.disabled = true;
    show("busy", "logging in…");
    let response;
    try {
      response = await fetch("/api/login", {
        method: "POST",
        headers: { "Content-Type": "application/x-www-form-urlencoded" },
        body,
        credentials: "same-origin",
        cache: "no-store",
      });
    } catch (_) {
      button.disabled = false;
      show("error", "cannot reach the console server (is it running? is the network up?)");
      return;
    }
    if (response.ok) {
      show("busy", "logged in, opening the console…");
      location.replace("/");
      return;
    }
    button.disabled = false;
    if (response.status === 401) {
      show("error", "wrong user or password");
      password.value = "";
      password.focus();
    } else if (response.status === 429) {
      show("error", (await errorText(response)) || "too many attempts: wait a moment and try again");
    } else {
      const text = await errorText(response);
      show("error", `the console server answered HTTP ${response.status}` + (text ? `: ${text}` : ""));
    }
  });
})();
