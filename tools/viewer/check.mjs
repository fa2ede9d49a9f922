// Drive the /viewer page in headless Chromium (Debian's, through playwright-core: no browser
// download) for tests/integration/test_viewer.py. Usage:
//   node check.mjs '{"url": ..., "surface": GML_ID, "point": [X, Y, Z], "values": [T, ...], "out": DIR}'
// url: the page with ?model=ID&key=KEY; surface: a facade's gml:id; point: an ECEF point on it;
// distance: the camera's distance from the point (m); values: temperatures (°C) whose colour-scale
// colours to report; out: folder for the screenshots.
// Steps: load, wait until the model is drawn, screenshot the view (overview.png); look at the point
// from in front of the facade, screenshot (facade.png), click the point; print one JSON object with what the page showed.
import { chromium } from "playwright-core";

const args = JSON.parse(process.argv[2]);
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  headless: true,
  // WebGL without a GPU: ANGLE on SwiftShader (software)
  args: ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox", "--disable-dev-shm-usage"],
});
const result = { console: [] };
try {
  const page = await browser.newPage({ viewport: { width: 1100, height: 700 }, deviceScaleFactor: 1 });
  page.on("console", (m) => m.type() === "error" && result.console.push(m.text()));
  page.on("pageerror", (e) => result.console.push(`pageerror: ${e.message}`));
  const t0 = Date.now();
  await page.goto(args.url);
  await page.waitForFunction(() => ["ready", "error"].includes(document.body.dataset.state), null, {
    timeout: 180_000,
  });
  result.state = await page.evaluate(() => document.body.dataset.state);
  result.loadMs = Date.now() - t0;
  result.message = await page.locator("#message").textContent();
  if (result.state === "ready") {
    const frame = () => page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
    await frame();
    const rect = (sel) => page.locator(sel).evaluate((e) => e.getBoundingClientRect().toJSON());
    result.canvas = await rect("#canvas");
    result.legend = await rect("#legend");
    await page.screenshot({ path: `${args.out}/overview.png` });
    result.framed = await page.evaluate((a) => window.citythermViewer.frameSurface(a.surface, a.point, a.distance), args);
    await frame();
    result.point = await page.evaluate((p) => window.citythermViewer.project(...p), args.point);
    result.colours = await page.evaluate((vs) => vs.map((v) => window.citythermViewer.legendColour(v)), args.values);
    await page.screenshot({ path: `${args.out}/facade.png` });
    await page.mouse.click(result.point.x, result.point.y);
    // the figures of the surface, then the facade figures and anomalies from the Features API
    await page.waitForFunction(
      (s) =>
        document.getElementById("info").dataset.surface === s &&
        !/loading/.test(document.getElementById("info-facade").textContent + document.getElementById("info-anomalies").textContent),
      args.surface,
      { timeout: 60_000 },
    );
    result.figures = await page.locator("#info-figures").innerText();
    result.facade = await page.locator("#info-facade").innerText();
    result.anomalies = await page.locator("#info-anomalies").innerText();
    result.jobs = await page.locator("#job-list").innerText();
  }
} finally {
  await browser.close();
}
process.stdout.write(JSON.stringify(result));
