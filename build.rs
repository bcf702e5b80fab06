//! Generates Embree bindings (bindgen over `ffi/embree.h`) and links Debian's Embree.
//!
//! Embree 3 is the default (Debian 12 has 3.13.5 and no pkg-config file for it);
//! `--features embree4` selects Embree 4. `EMBREE_DIR` may name an install prefix
//! holding `include/` and `lib/`.
use std::env;
use std::path::{Path, PathBuf};

fn main() {
    println!("cargo:rerun-if-env-changed=EMBREE_DIR");
    println!("cargo:rerun-if-changed=ffi/embree.h");
    println!("cargo:rerun-if-changed=build.rs");

    let embree4 = env::var_os("CARGO_FEATURE_EMBREE4").is_some();
    let (version, lib) = if embree4 {
        ("embree4", "embree4")
    } else {
        ("embree3", "embree3")
    };

    let mut include_dirs: Vec<PathBuf> = Vec::new();
    let mut lib_dirs: Vec<PathBuf> = Vec::new();
    if let Some(dir) = env::var_os("EMBREE_DIR") {
        let dir = PathBuf::from(dir);
        include_dirs.push(dir.join("include"));
        lib_dirs.push(dir.join("lib"));
        lib_dirs.push(dir.join("lib64"));
    }
    include_dirs.extend(["/usr/include", "/usr/local/include"].map(PathBuf::from));
    lib_dirs.extend(
        [
            "/usr/lib/x86_64-linux-gnu",
            "/usr/lib/aarch64-linux-gnu",
            "/usr/lib",
            "/usr/local/lib",
        ]
        .map(PathBuf::from),
    );

    let header = format!("{version}/rtcore.h");
    let Some(include) = include_dirs.iter().find(|d| d.join(&header).is_file()) else {
        panic!(
            "Embree not found: no {header} under {}. Install it (Debian 12: `apt-get install libembree-dev`, \
             or run scripts/setup.sh) or set EMBREE_DIR to an Embree install prefix with include/ and lib/.",
            include_dirs
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    };
    let lib_found = lib_dirs.iter().find(|d| has_lib(d, lib));
    match lib_found {
        Some(dir) => println!("cargo:rustc-link-search=native={}", dir.display()),
        None => panic!(
            "Embree header found in {} but no lib{lib}.so in {}; set EMBREE_DIR to the Embree install prefix.",
            include.display(),
            lib_dirs
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
    println!("cargo:rustc-link-lib=dylib={lib}");

    let mut builder = bindgen::Builder::default()
        .header("ffi/embree.h")
        .clang_arg(format!("-I{}", include.display()))
        .allowlist_function("rtc.*")
        .allowlist_type("RTC.*")
        .allowlist_var("RTC.*")
        .default_enum_style(bindgen::EnumVariation::ModuleConsts)
        .derive_default(true)
        .layout_tests(false)
        .parse_callbacks(Box::new(bindgen::CargoCallbacks::new()));
    if embree4 {
        builder = builder.clang_arg("-DGS4CITY_EMBREE4");
    }
    let bindings = builder.generate().unwrap_or_else(|e| {
        panic!(
            "bindgen failed on ffi/embree.h ({e}). bindgen needs libclang and its builtin headers: \
             `apt-get install libclang-dev` (Debian 12)."
        )
    });
    let out = PathBuf::from(env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    bindings
        .write_to_file(out.join("embree_sys.rs"))
        .expect("write embree_sys.rs into OUT_DIR");
}

fn has_lib(dir: &Path, lib: &str) -> bool {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    entries.flatten().any(|e| {
        let name = e.file_name();
        let name = name.to_string_lossy();
        name.starts_with(&format!("lib{lib}.so"))
    })
}
