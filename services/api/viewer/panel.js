// The side panel's lists: a clicked surface's figures of the analysis and its building's anomalies
// (OGC API - Features: `/collections/facades/items`, `/collections/anomalies/items`) and the jobs
// (`GET /jobs`). Text only: nothing from the data becomes markup.
import { fetchJson } from "./api.js";

const ZERO_C_K = 273.15;
const $ = (id) => document.getElementById(id);
const kelvin = (k) => (k === null || k === undefined ? "—" : `${(k - ZERO_C_K).toFixed(1)} °C`);
const num = (v, digits, unit = "") => (v === null || v === undefined ? "—" : `${Number(v).toFixed(digits)}${unit}`);

/** Fill a <dl> with [term, value] pairs (text only: nothing from the data becomes markup). */
export function fillList(dl, pairs) {
  dl.replaceChildren(
    ...pairs.flatMap(([t, v]) => {
      const dt = document.createElement("dt");
      const dd = document.createElement("dd");
      dt.textContent = t;
      dd.textContent = v ?? "—";
      return [dt, dd];
    }),
  );
}

/** A list item with `text`. */
export function item(text) {
  const li = document.createElement("li");
  li.textContent = text;
  return li;
}

/** The OGC API - Features query of a building's features of a model (name) and theme. */
function featuresQuery(collection, { building, model, theme }) {
  const q = new URLSearchParams({ building, limit: "1000" });
  if (model) q.set("model", model);
  if (theme) q.set("theme", theme);
  return `collections/${collection}/items?${q}`;
}

/** The facade's figures of the analysis (`/collections/facades/items`, this surface's rows) into
 * `#info-facade`; `where`: `{building, surface, model, theme}`. */
export async function showFacade(where) {
  const { surface } = where;
  const dl = $("info-facade");
  fillList(dl, [["…", "loading"]]);
  try {
    const doc = await fetchJson(featuresQuery("facades", where));
    const rows = doc.features.filter((f) => f.properties.surface_gml_id === surface);
    if (!rows.length) return fillList(dl, [["—", "no figures for this surface"]]);
    const f = rows[rows.length - 1].properties; // the newest appearance (highest id)
    fillList(dl, [
      ["Median", kelvin(f.median_k)],
      ["5–95 %", `${kelvin(f.p05_k)} … ${kelvin(f.p95_k)}`],
      ["Std dev", num(f.std_k, 2, " K")],
      ["Typical", kelvin(f.typical_k)],
      ["Hot share", f.hot_share == null ? "—" : num(100 * f.hot_share, 1, " %")],
      ["Heat loss index", num(f.heat_loss_index, 2)],
      ["Resolution", num(f.resolution_m, 3, " m")],
      ["View angle", num(f.view_angle_deg, 0, "°")],
      ["Area", num(f.area_m2, 1, " m²")],
      ["Job", f.job ?? "—"],
    ]);
  } catch (err) {
    fillList(dl, [["!", err.message]]);
  }
}

/** The building's anomalies (`/collections/anomalies/items`), those of the surface first, into
 * `#info-anomalies`; `where` as for `showFacade`. */
export async function showAnomalies(where) {
  const { surface } = where;
  const ul = $("info-anomalies");
  ul.replaceChildren(item("loading…"));
  try {
    const doc = await fetchJson(featuresQuery("anomalies", where));
    const rows = doc.features.map((f) => f.properties);
    rows.sort((a, b) => (b.surface_gml_id === surface) - (a.surface_gml_id === surface));
    ul.replaceChildren(
      ...(rows.length ? [] : [item("none found")]),
      ...rows.map((a) => {
        const on = a.surface_gml_id === surface ? "this surface" : (a.surface_gml_id ?? "?");
        const d = a.peak_delta_k;
        const peak = d == null ? "—" : `${d >= 0 ? "+" : "−"}${num(Math.abs(d), 1, " K")}`;
        return item(`${a.kind}: ${num(a.area_m2, 2, " m²")}, peak ${peak} (${on})`);
      }),
    );
  } catch (err) {
    ul.replaceChildren(item(err.message));
  }
}

/** A jobs list entry: short id, status, stage, progress (bar), model, time and message;
 * `modelId`: the shown model (its jobs are marked). */
export function jobItem(j, modelId) {
  const li = document.createElement("li");
  li.className = `job-${j.status}${j.inputs?.model === modelId ? " job-this-model" : ""}`;
  li.dataset.job = j.jobID;
  const head = document.createElement("div");
  const model = j.inputs?.model === undefined ? "" : ` · model #${j.inputs.model}`;
  head.textContent = `${j.jobID.slice(0, 8)} · ${j.status} · ${j.stage} · ${j.progress} %${model}`;
  const bar = document.createElement("progress");
  bar.max = 100;
  bar.value = j.progress;
  const when = document.createElement("small");
  when.textContent = [j.updated ?? j.created, j.message].filter(Boolean).join(" · ");
  li.append(head, bar, when);
  return li;
}
