// Opens Foxglove Studio 1.48's own app (host.js, index.html) in headless Chromium on a live
// Foxglove WebSocket server or a bag, loads each layout in turn and reports what every Plot
// panel of it drew, read from the app's React tree (host.js's window.imView), as one JSON
// line on stdout. Optionally saves a 1280x800 PNG of each layout.
//
//   node view.mjs --layouts DIR (--ws ws://127.0.0.1:PORT | --bag FILE.mcap)
//                 [--screenshots DIR [--shots NAME,...] [--suffix _live]] [--timeout S]
//                 [--subprotocol foxglove.sdk.v1] [--ready FILE] [--serve]
//
// Each layout (DIR/*.json, a layout's id is its file name) is shown in the app, every Tab
// panel's tabs in turn; a view is done when each of its Plot panels has a point on every
// path, or after --timeout seconds (its panels are then reported as they are). A bag: one
// app, the layouts selected one after another, a layout with an experiment-rate plot in an
// app of its own. Live: an app per view (a layout or a tab of
// it), all at once (a run may last seconds), each then read until the server goes away
// ("last": Fig. 9's every loss); --ready FILE: written once every live app has loaded (and
// retries its connection every 3 s), so that a run started then is seen from its start.
// --serve only serves the page and prints its address, for
// a browser of one's own. Chromium is Debian's (/usr/bin/chromium, or $CHROMIUM), closed in
// a finally block.
import { chromium } from "playwright-core";
import { createServer } from "node:http";
import { mkdtemp, readFile, readdir, rm, writeFile } from "node:fs/promises";
import { tmpdir } from "node:os";
import { basename, dirname, extname, join } from "node:path";
import { fileURLToPath } from "node:url";
import { parseArgs } from "node:util";

const HERE = dirname(fileURLToPath(import.meta.url));
// The WebSocket subprotocol Studio 1.48's client offers (@foxglove/ws-protocol); foxglove-sdk's
// server (0.5 to 0.30) accepts only "foxglove.sdk.v1". --subprotocol NAME serves the app with
// this one constant rewritten to NAME: so changed, the app talks to foxglove-sdk 0.30.0's
// server and plots its data (checked by hand, 2026-12-05); nothing else is changed.
const STUDIO_SUBPROTOCOL = "foxglove.websocket.v1";
const SUBPROTOCOL_CONSTANT = (name) => `FoxgloveClient.SUPPORTED_SUBPROTOCOL = "${name}"`;
const { values: opt } = parseArgs({
  options: {
    layouts: { type: "string" },
    ws: { type: "string" },
    bag: { type: "string" },
    shots: { type: "string" },
    screenshots: { type: "string" },
    suffix: { type: "string", default: "" },
    timeout: { type: "string", default: "60" },
    subprotocol: { type: "string", default: STUDIO_SUBPROTOCOL },
    ready: { type: "string" },
    serve: { type: "boolean", default: false },
  },
});
if (!opt.layouts || !!opt.ws === !!opt.bag) {
  console.error("usage: node view.mjs --layouts DIR (--ws URL | --bag FILE) [--screenshots DIR [--shots NAME,...] [--suffix S]] [--timeout S] [--subprotocol NAME] [--serve]");
  process.exit(2);
}
const TIMEOUT_MS = Number(opt.timeout) * 1000;
const names = (await readdir(opt.layouts)).filter((f) => f.endsWith(".json")).sort();
const layouts = Object.fromEntries(
  await Promise.all(names.map(async (f) => [basename(f, ".json"), JSON.parse(await readFile(join(opt.layouts, f), "utf8"))])),
);

// -- the page, the app's bundle, React and the bag over HTTP on 127.0.0.1 --------------------
const TYPES = { ".js": "text/javascript", ".html": "text/html", ".json": "application/json", ".wasm": "application/wasm", ".png": "image/png", ".svg": "image/svg+xml", ".woff2": "font/woff2", ".ttf": "font/ttf", ".css": "text/css" };
const ROUTES = [
  ["/assets/", join(HERE, "node_modules/@foxglove/studio-base/assets/")],
  ["/react/", join(HERE, "node_modules/react/")],
  ["/react-dom/", join(HERE, "node_modules/react-dom/")],
];
const server = createServer(async (req, res) => {
  const path = decodeURIComponent(new URL(req.url, "http://x").pathname);
  let file;
  if (path === "/" || path === "/index.html") file = join(HERE, "index.html");
  else if (path === "/host.js") file = join(HERE, "host.js");
  else if (path === "/bag.mcap" && opt.bag) file = opt.bag;
  else if (path === "/layouts.json") return res.writeHead(200, { "content-type": TYPES[".json"] }).end(JSON.stringify(layouts));
  else for (const [prefix, dir] of ROUTES) if (path.startsWith(prefix) && !path.includes("..")) file = join(dir, path.slice(prefix.length));
  try {
    let body = await readFile(file);
    if (path === "/assets/index.js" && opt.subprotocol !== STUDIO_SUBPROTOCOL) {
      const text = body.toString("utf8");
      if (!text.includes(SUBPROTOCOL_CONSTANT(STUDIO_SUBPROTOCOL))) throw new Error("no subprotocol constant in the app");
      body = text.replace(SUBPROTOCOL_CONSTANT(STUDIO_SUBPROTOCOL), SUBPROTOCOL_CONSTANT(opt.subprotocol));
    }
    res.writeHead(200, { "content-type": TYPES[extname(file)] ?? "application/octet-stream" }).end(body);
  } catch {
    res.writeHead(404).end();
  }
});
await new Promise((ok) => server.listen(0, "127.0.0.1", ok));
const base = `http://127.0.0.1:${server.address().port}/`;
const source = opt.ws ? `ds=foxglove-websocket&ds.url=${encodeURIComponent(opt.ws)}` : "ds=im-tuner-bag&bag=/bag.mcap";
if (opt.serve) {
  // the page alone, for a browser of one's own: prints its address, serves until ended
  console.log(`${base}?${source}&layoutId=${encodeURIComponent(basename(names[0], ".json"))}`);
  await new Promise(() => {});
}

// -- what a layout shows ------------------------------------------------------------------------
function leaves(node) {
  return typeof node === "string" ? [node] : [...leaves(node.first), ...leaves(node.second)];
}
/** The views of a layout: the Plot panels shown at once, and the tabs to choose for them. */
function views(layout) {
  const out = [{ tabs: [], plots: [] }];
  for (const id of leaves(layout.layout)) {
    if (id.startsWith("Tab!")) {
      layout.configById[id].tabs.forEach((tab, i) => out.push({ tabs: [[id, i]], plots: leaves(tab.layout).filter((p) => p.startsWith("Plot!")) }));
    } else if (id.startsWith("Plot!")) out[0].plots.push(id);
  }
  return out.filter((v) => v.plots.length > 0);
}
/** A page of the app with layout `layoutId`, its player made (not yet connected). */
async function loadApp(context, layoutId) {
  const page = await context.newPage();
  page.on("pageerror", (e) => errors.push(String(e).slice(0, 300)));
  await page.goto(`${base}?${source}&layoutId=${encodeURIComponent(layoutId)}`, { timeout: TIMEOUT_MS });
  await page.waitForFunction(() => !!window.imView?.state(), null, { timeout: TIMEOUT_MS, polling: 100 });
  return page;
}
/** `page` once its data source is there (a live page retries its connection every 3 s
 * until the server is up). */
async function connected(page) {
  await page.waitForFunction(() => window.imView?.state()?.presence === "PRESENT", null, { timeout: TIMEOUT_MS, polling: 100 });
  return page;
}
const openApp = async (context, layoutId) => connected(await loadApp(context, layoutId));

const t0 = Date.now();
const seconds = () => (Date.now() - t0) / 1000;
const presence = (page) => page.evaluate(() => window.imView.state()?.presence);

/** Shows the views of layout `name` on `page` in turn (all, or the one numbered `only`),
 * each until its Plot panels all have a point on every path (or TIMEOUT_MS); returns the
 * panels as they were then, and when. */
async function showLayout(page, name, shot, only) {
  const panels = {};
  const full = {};
  for (const [i, view] of views(layouts[name]).entries()) {
    if (only !== undefined && i !== only) continue;
    for (const [tabPanel, index] of view.tabs) await page.evaluate(([p, k]) => window.imView.selectTab(p, k), [tabPanel, index]);
    // full: a point on every path. The player reads a bag in blocks and the panels fill as
    // they come: a bag's view with an experiment-rate plot (a custom x axis: Fig. 9, whose
    // every point is checked) or a screenshot's also waits until it settled (no point added
    // and no block read for 1 s: a run's experiments can be hundreds of blocks apart); the
    // app's player state (read with the panels) says which of the player's blocks were not
    // read for them; the 5 kHz views are done at their first points (their whole run takes
    // minutes to plot on 2 cores).
    const custom = view.plots.some((id) => layouts[name].configById[id].xAxisVal === "custom");
    await page.evaluate(() => delete window.imSettle); // each view settles on its own points
    await page
      .waitForFunction(
        ([ids, settle]) => {
          const counts = window.imView.counts();
          const full = ids.every((id) => counts[id] && Object.values(counts[id]).every((n) => n > 0));
          const n = ids.reduce((a, id) => a + Object.values(counts[id] ?? {}).reduce((b, k) => b + k, 0), 0);
          const key = settle ? `${n} ${window.imView.preloaded()}` : ""; // points, blocks read
          const w = (window.imSettle ??= { key: "", since: 0 });
          if (key !== w.key) Object.assign(w, { key, since: Date.now() });
          return full && (!settle || Date.now() - w.since >= 1000);
        },
        [view.plots, !!opt.bag && (custom || (shot && i === 0))],
        { timeout: TIMEOUT_MS, polling: 100 },
      )
      .catch(() => {});
    const plots = await page.evaluate(() => window.imView.plots());
    for (const id of view.plots) {
      panels[id] = plots[id] ?? null;
      full[id] = seconds();
    }
    if (shot && i === 0) {
      await page.evaluate(() => window.imView.closeSidebars());
      await page.waitForTimeout(2000); // the chart worker draws the points it was sent
      await page.screenshot({ path: join(opt.screenshots, `${name}${opt.suffix}.png`) });
    }
  }
  return { panels, at: full, state: await page.evaluate(() => window.imView.state()) };
}
const shots = (name) => !!opt.screenshots && (!opt.shots || opt.shots.split(",").includes(name));

const errors = [];
const report = { source: opt.ws ?? opt.bag, layouts: {}, errors };
const profile = await mkdtemp(join(tmpdir(), "im-tuner-foxglove-view-"));
let context;
try {
  // a fresh profile, launched as Playwright requires for a --user-data-dir of one's own
  context = await chromium.launchPersistentContext(profile, {
    executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
    headless: true,
    viewport: { width: 1280, height: 800 },
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync"],
  });
  if (opt.bag) {
    // after the fact: one app, the layouts selected one after another; a layout with an
    // experiment-rate plot (every point checked) in an app of its own. In one app the
    // layouts share its player's block cache, and its block loader (Studio 1.48) skips the
    // block after each run of blocks that lack the same topics: a layout shown after
    // others could miss a block's messages for good.
    const own = (name) => Object.values(layouts[name].configById).some((c) => c.xAxisVal === "custom");
    let shared;
    for (const name of Object.keys(layouts)) {
      const page = own(name) ? await openApp(context, name) : (shared ??= await openApp(context, name));
      if (page === shared) await page.evaluate((id) => window.imView.selectLayout(id), name);
      report.layouts[name] = await showLayout(page, name, shots(name));
      if (page !== shared) await page.close();
    }
  } else {
    // live: an app per view (a layout, or a tab of it), all connected while the run goes on
    // (it may last seconds); each view is then read until the server goes away ("last":
    // Fig. 9's every loss)
    const all = Object.keys(layouts).flatMap((name) => views(layouts[name]).map((_v, i) => [name, i]));
    const pages = await Promise.all(all.map(([name]) => loadApp(context, name)));
    if (opt.ready) await writeFile(opt.ready, `${pages.length}\n`);
    const seen = await Promise.all(
      all.map(async ([name, i], k) => {
        const page = await connected(pages[k]);
        const shown = await showLayout(page, name, shots(name) && i === 0, i);
        let last = {};
        while ((await presence(page)) === "PRESENT") {
          last = await page.evaluate(() => window.imView.plots());
          await page.waitForTimeout(250);
        }
        shown.last = last;
        shown.disconnected = seconds();
        return [name, shown];
      }),
    );
    for (const [name, shown] of seen) {
      const r = (report.layouts[name] ??= { panels: {}, at: {}, last: {}, state: shown.state, disconnected: 0 });
      Object.assign(r.panels, shown.panels);
      Object.assign(r.at, shown.at);
      Object.assign(r.last, shown.last);
      r.disconnected = Math.max(r.disconnected, shown.disconnected);
    }
  }
} finally {
  await context?.close();
  server.close();
  await rm(profile, { recursive: true, force: true });
}
console.log(JSON.stringify(report));
