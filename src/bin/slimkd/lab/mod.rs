//! The lab: the experiments of the papers run over the library (the
//! `report`, `sweep` and `calibrate` commands), their charts, and the
//! figures and JSON the commands share.

pub(crate) mod calibrate;
pub(crate) mod figures;
pub(crate) mod plot;
pub(crate) mod report;
#[cfg(test)]
mod test_dirs;
