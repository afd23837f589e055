// Mounts Foxglove Studio's App (studio-base 1.48) with:
// - the layouts of /layouts.json in an in-memory layout storage (a layout's id is its name),
// - the app's own data sources: the Foxglove WebSocket client, and the MCAP local-file source
//   fed the file at ?bag=URL (fetched first, handed to the app as a File, as "Open local file"),
// - the URL's deep link (?ds=...&ds.url=...&layoutId=...), as app.foxglove.dev reads it.
// window.imView exposes what the driver (view.mjs) reads from the app's React tree.
/* global React, ReactDOM, App, FoxgloveWebSocketDataSourceFactory, McapLocalDataSourceFactory */
(async () => {
  const query = new URLSearchParams(location.search);
  const layouts = await (await fetch("/layouts.json")).json();
  const savedAt = new Date().toISOString();
  const stored = new Map(
    Object.entries(layouts).map(([name, data]) => [
      name,
      { id: name, name, permission: "CREATOR_WRITE", baseline: { data, savedAt }, working: undefined, syncInfo: undefined },
    ]),
  );
  const layoutStorage = {
    list: async () => [...stored.values()],
    get: async (_ns, id) => stored.get(id),
    put: async (_ns, layout) => (stored.set(layout.id, layout), layout),
    delete: async (_ns, id) => void stored.delete(id),
    importLayouts: async () => {},
  };
  const settings = new Map([
    ["launchPreference", "web"],
    ["ui.open-dialog-startup", false],
    ["telemetry.telemetryEnabled", false],
    ["telemetry.crashReportingEnabled", false],
    ["updates.enabled", false],
    ["hideSignInPrompt", true],
    ["colorScheme", "light"],
  ]);
  const listeners = new Map();
  const appConfiguration = {
    get: (key) => settings.get(key),
    set: async (key, value) => {
      settings.set(key, value);
      for (const cb of listeners.get(key) ?? []) cb(value);
    },
    addChangeListener: (key, cb) => listeners.set(key, [...(listeners.get(key) ?? []), cb]),
    removeChangeListener: (key, cb) => listeners.set(key, (listeners.get(key) ?? []).filter((c) => c !== cb)),
  };
  const dataSources = [new FoxgloveWebSocketDataSourceFactory()];
  const bagUrl = query.get("bag");
  if (bagUrl) {
    const bytes = await (await fetch(bagUrl)).arrayBuffer();
    const file = new File([bytes], bagUrl.split("/").pop(), { type: "application/octet-stream" });
    const mcap = new McapLocalDataSourceFactory();
    // the app's MCAP file source, given the file as the open-file dialog gives it
    dataSources.push({
      id: "im-tuner-bag",
      type: "connection",
      displayName: "im_tuner bag",
      initialize: (args) => mcap.initialize({ ...args, file }),
    });
  }
  ReactDOM.render(
    React.createElement(App, {
      deepLinks: [location.href],
      appConfiguration,
      dataSources,
      layoutStorage,
      extensionLoaders: [],
      enableGlobalCss: true,
    }),
    document.getElementById("root"),
  );
  window.imView = makeProbe();
})();

// What the app holds, read from its React tree (React 17 keeps each DOM node's fiber under a
// "__reactFiber$..." key): the message pipeline's store, the current layout's actions, and
// every Plot panel's datasets (the props of its chart: the points the panel draws).
function makeProbe() {
  const rootFiber = () => {
    const el = document.getElementById("root");
    const c = el._reactRootContainer?._internalRoot?.current;
    return c;
  };
  function* walk(fiber) {
    const stack = [fiber];
    while (stack.length) {
      const f = stack.pop();
      if (!f) continue;
      yield f;
      if (f.sibling) stack.push(f.sibling);
      if (f.child) stack.push(f.child);
    }
  }
  const find = (pred) => {
    for (const f of walk(rootFiber())) if (pred(f)) return f;
    return undefined;
  };
  // the message pipeline's store (a zustand store in a context provider's value)
  const pipeline = () =>
    find((f) => {
      const v = f.memoizedProps?.value;
      return typeof v?.getState === "function" && v.getState()?.public?.playerState !== undefined;
    })?.memoizedProps.value.getState();
  const layoutActions = () => find((f) => typeof f.memoizedProps?.value?.actions?.setSelectedLayoutId === "function")?.memoizedProps.value.actions;
  const panelId = (fiber) => {
    for (let f = fiber; f; f = f.return) if (typeof f.memoizedProps?.childId === "string") return f.memoizedProps.childId;
    return undefined;
  };
  // each Plot panel's chart props, by panel id: its x axis and, per path, the points drawn
  // (a path's points may be split over several datasets at gaps: gathered by path)
  const charts = () => {
    const out = {};
    for (const f of walk(rootFiber())) {
      const p = f.memoizedProps;
      if (p && Array.isArray(p.paths) && Array.isArray(p.datasets) && "xAxisVal" in p) {
        out[panelId(f)] = { xAxisVal: p.xAxisVal, paths: p.paths.map((x) => x.value), datasets: p.datasets };
      }
    }
    return out;
  };
  // the app puts a point {x: NaN, y: NaN, value: ""} between two ranges of a path's data, a
  // break in the line: not a datum
  const isBreak = (pt) => pt.value === "" && Number.isNaN(pt.x) && Number.isNaN(pt.y);
  const eachPoint = (chart, path, fn) => {
    for (const d of chart.datasets) for (const pt of d.data ?? []) if (pt.path === path && !isBreak(pt)) fn(pt);
  };
  // per panel, per path: the number of points (cheap enough to poll)
  const counts = () => {
    const out = {};
    for (const [id, c] of Object.entries(charts())) {
      out[id] = Object.fromEntries(c.paths.map((path) => [path, 0]));
      for (const d of c.datasets) for (const pt of d.data ?? []) if (pt.path in out[id] && !isBreak(pt)) out[id][pt.path] += 1;
    }
    return out;
  };
  // per panel, per path: the number of points, whether all are finite, and for a plot
  // against a custom x axis (Fig. 9: a point per experiment) the points [x, y]
  const plots = () => {
    const out = {};
    for (const [id, c] of Object.entries(charts())) {
      out[id] = {};
      for (const path of c.paths) {
        const s = { n: 0, finite: true, ...(c.xAxisVal === "custom" ? { points: [] } : {}) };
        eachPoint(c, path, (pt) => {
          s.n += 1;
          s.finite &&= Number.isFinite(pt.x) && Number.isFinite(pt.y);
          s.points?.push([pt.x, pt.y]);
        });
        out[id][path] = s;
      }
    }
    return out;
  };
  // the player's blocks (its message cache), each with the subscribed topics it lacks
  const unreadTopics = (s) => {
    const topics = [...(s?.subscriberIdsByTopic.keys() ?? [])];
    return (s?.public.playerState.progress?.messageCache?.blocks ?? []).map((b) => (b ? topics.filter((t) => !b.messagesByTopic[t]) : "none"));
  };
  const preloaded = (s) => {
    const lack = unreadTopics(s);
    return lack.length ? lack.filter((m) => m.length === 0).length / lack.length : 0;
  };
  return {
    state() {
      const s = pipeline();
      return s && {
        presence: s.public.playerState.presence,
        name: s.public.playerState.name,
        problems: (s.public.playerState.problems ?? []).map((p) => p.message),
        topics: s.public.sortedTopics.map((t) => t.name),
        subscribed: [...s.subscriberIdsByTopic.keys()].sort(),
        received: [...s.lastMessageEventByTopic.keys()].sort(),
        // how much of a bag the player has read ahead for playback: a fraction of its time range
        loaded: (s.public.playerState.progress?.fullyLoadedFractionRanges ?? []).reduce((a, r) => a + r.end - r.start, 0),
        // how much of it the panels' preloaded topics are read for: the fraction of the
        // player's blocks (its message cache) that hold every subscribed topic
        preloaded: preloaded(s),
        // the first blocks not read for them: [index, the topics it lacks, or "none"]
        unread: unreadTopics(s).flatMap((m, i) => (m.length ? [[i, m]] : [])).slice(0, 12),
      };
    },
    plots,
    counts,
    preloaded: () => preloaded(pipeline()),
    selectLayout(id) {
      layoutActions().setSelectedLayoutId(id);
    },
    // the sidebars closed, for a screenshot of the panels alone (the workspace's own store)
    closeSidebars() {
      const store = find((f) => typeof f.memoizedProps?.value?.getState?.()?.leftSidebarOpen === "boolean")?.memoizedProps.value;
      store?.setState({ sidebarItem: undefined, leftSidebarOpen: false, rightSidebarOpen: false });
    },
    // a Tab panel's tab, chosen as a click on its title does (the app's own action)
    selectTab(panel, index) {
      layoutActions().savePanelConfigs({ configs: [{ id: panel, config: { activeTabIdx: index } }] });
    },
  };
}
