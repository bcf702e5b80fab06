//! Simulated SAM masks and simulated CLIP features (placeholder).
