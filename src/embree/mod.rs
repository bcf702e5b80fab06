//! The Embree FFI: the only module of gs4city allowed to use `unsafe`.
#![allow(unsafe_code)]
pub(crate) mod sys;
