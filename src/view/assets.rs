//! The files of the page, embedded in the binary at build time: the page and its script (ours)
//! and the splat renderer they import, vendored from npm with its licences (`vendor/`: Spark
//! `@sparkjsdev/spark` and three.js, copied by `scripts/vendor_viewer.sh` from the versions
//! pinned in `tools/js/package-lock.json`). An installed `gs4city` serves them without the
//! checkout, npm or the network.

/// One embedded file: its URL path, its media type, its bytes.
pub struct Asset {
    pub path: &'static str,
    pub content_type: &'static str,
    pub bytes: &'static [u8],
}

const JS: &str = "text/javascript; charset=utf-8";
const TEXT: &str = "text/plain; charset=utf-8";
const HTML: &str = "text/html; charset=utf-8";

/// An [`Asset`] of the file `src/view/FILE` served at `/URL`.
macro_rules! asset {
    ($url:literal, $ty:expr, $file:literal) => {
        Asset {
            path: $url,
            content_type: $ty,
            bytes: include_bytes!($file),
        }
    };
}

/// Every file the page loads, by URL path.
pub const ASSETS: &[Asset] = &[
    asset!("/", HTML, "page.html"),
    asset!("/index.html", HTML, "page.html"),
    asset!("/viewer.js", JS, "viewer.js"),
    asset!(
        "/vendor/spark.module.min.js",
        JS,
        "vendor/spark.module.min.js"
    ),
    asset!(
        "/vendor/three.module.min.js",
        JS,
        "vendor/three.module.min.js"
    ),
    asset!("/vendor/three.core.min.js", JS, "vendor/three.core.min.js"),
    asset!(
        "/vendor/three/addons/postprocessing/Pass.js",
        JS,
        "vendor/three/addons/postprocessing/Pass.js"
    ),
    asset!("/vendor/LICENSE.spark", TEXT, "vendor/LICENSE.spark"),
    asset!("/vendor/LICENSE.three", TEXT, "vendor/LICENSE.three"),
];

/// The embedded file served at URL path `path`.
pub fn find(path: &str) -> Option<&'static Asset> {
    ASSETS.iter().find(|a| a.path == path)
}
