// How the project's browser scripts start a browser (cesium_shot.mjs, view_click.mjs,
// view_timing.mjs): Debian's Chromium ($CHROMIUM or /usr/bin/chromium; playwright-core downloads
// none) headless through playwright-core, WebGL on SwiftShader (the CPU), and without the
// background connections that a machine with no network would refuse.
import { chromium } from 'playwright-core';

export const CHROMIUM_ARGS = ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
  '--ignore-gpu-blocklist', '--disable-quic', '--no-first-run', '--disable-background-networking',
  '--disable-component-update', '--disable-sync'];

export function launchChromium() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: CHROMIUM_ARGS,
  });
}
