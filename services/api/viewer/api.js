// API access of the viewer page: the API's base URL (`../` of the page) and the API key of this tab
// (sessionStorage; asked for once in a dialog, or taken from `?key=`), sent as
// `Authorization: Bearer` with every request (docs/viewer.md, "Access").

/** The API's base URL. */
export const API = new URL("../", location.href);
const KEY_ITEM = "citytherm.apiKey"; // sessionStorage: this tab only, gone when it closes
const $ = (id) => document.getElementById(id);
let keyPrompt = null; // the open key dialog's promise, shared by concurrent 401s

/** Take `?key=` from the address (kept in sessionStorage, removed from the address bar). */
export function keyFromAddress() {
  const url = new URL(location.href);
  const key = url.searchParams.get("key");
  if (key) {
    sessionStorage.setItem(KEY_ITEM, key);
    url.searchParams.delete("key");
    history.replaceState(null, "", url);
  }
}

/** Ask the user for an API key (one dialog for every request waiting on it). */
export function askKey() {
  keyPrompt ??= new Promise((resolve) => {
    const dialog = $("key-dialog");
    $("key-form").onsubmit = () => {
      sessionStorage.setItem(KEY_ITEM, $("key-input").value.trim());
      $("key-input").value = "";
      keyPrompt = null;
      resolve();
    };
    dialog.showModal();
  });
  return keyPrompt;
}

/** `fetch` of an API URL with the key; asks for a key on 401 and tries again. Throws an Error
 * with the problem's detail on any other failure. */
async function apiFetch(url) {
  for (;;) {
    const key = sessionStorage.getItem(KEY_ITEM);
    const headers = key ? { Authorization: `Bearer ${key}` } : {};
    const r = await fetch(new URL(url, API), { headers });
    if (r.status === 401) {
      sessionStorage.removeItem(KEY_ITEM);
      await askKey();
      continue;
    }
    if (!r.ok) {
      const problem = await r.json().catch(() => ({}));
      const err = new Error(problem.detail ?? `${r.status} ${r.statusText}`);
      err.status = r.status;
      throw err;
    }
    return r;
  }
}
export const fetchJson = async (url) => (await apiFetch(url)).json();
export const fetchBytes = async (url) => (await apiFetch(url)).arrayBuffer();


/** Forget the key of this tab. */
export function forgetKey() {
  sessionStorage.removeItem(KEY_ITEM);
}
