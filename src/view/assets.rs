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

/// Every file the page loads, by URL path.
pub const ASSETS: &[Asset] = &[
    Asset {
        path: "/",
        content_type: "text/html; charset=utf-8",
        bytes: include_bytes!("page.html"),
    },
    Asset {
        path: "/index.html",
        content_type: "text/html; charset=utf-8",
        bytes: include_bytes!("page.html"),
    },
    Asset {
        path: "/viewer.js",
        content_type: JS,
        bytes: include_bytes!("viewer.js"),
    },
    Asset {
        path: "/vendor/spark.module.min.js",
        content_type: JS,
        bytes: include_bytes!("vendor/spark.module.min.js"),
    },
    Asset {
        path: "/vendor/three.module.min.js",
        content_type: JS,
        bytes: include_bytes!("vendor/three.module.min.js"),
    },
    Asset {
        path: "/vendor/three.core.min.js",
        content_type: JS,
        bytes: include_bytes!("vendor/three.core.min.js"),
    },
    Asset {
        path: "/vendor/three/addons/postprocessing/Pass.js",
        content_type: JS,
        bytes: include_bytes!("vendor/three/addons/postprocessing/Pass.js"),
    },
    Asset {
        path: "/vendor/LICENSE.spark",
        content_type: TEXT,
        bytes: include_bytes!("vendor/LICENSE.spark"),
    },
    Asset {
        path: "/vendor/LICENSE.three",
        content_type: TEXT,
        bytes: include_bytes!("vendor/LICENSE.three"),
    },
];

/// The embedded file served at URL path `path`.
pub fn find(path: &str) -> Option<&'static Asset> {
    ASSETS.iter().find(|a| a.path == path)
}

/// Bytes of everything embedded (the page, its script and the vendored renderer).
pub fn total_bytes() -> usize {
    ASSETS
        .iter()
        .filter(|a| a.path != "/index.html")
        .map(|a| a.bytes.len())
        .sum()
}
