//! The mixing chamber between the syringes and the nozzle, described by its
//! residence-time distribution and stepped in volume pushed (not time), so it holds at
//! any flow rate. Pure: numbers in, numbers out.
//!
//! # Models
//!
//! A chamber of volume V (`volume_nl`) is a plug-flow section of volume V_p followed by
//! N equal well-mixed tanks in series of volume V_t in all (V_p + V_t = V):
//!
//! - **plug** (`MixerModel::Plug`): V_p = V, no tanks. A composition pushed in now leaves
//!   the nozzle exactly V later (first in, first out). This is the planner's mixing lead
//!   and hil-sim's chamber before mixer models existed, number for number.
//! - **mixed** (`MixerModel::Mixed`): one well-mixed tank of V. After a step in the
//!   inflow from c0 to c1 the outflow is c1 + (c0 − c1)·e^(−v/V) after v pushed.
//!   Mean residence volume V, variance V².
//! - **dispersion** (`MixerModel::Dispersion`): plug flow with axial dispersion, Peclet
//!   number Pe (`peclet`), with closed–closed (Danckwerts) boundaries: the residence
//!   volume has mean V and variance V²·σ²θ with σ²θ = 2/Pe − 2/Pe²·(1 − e^(−Pe)).
//!   It is modelled as N = min(⌊1/σ²θ⌋, [`MAX_TANKS`]) tanks of V_t = V·√(N·σ²θ) in all
//!   after a plug section of V − V_t: the mean and the variance are exactly those of the
//!   dispersion model (a tank chain has variance V_t²/N); the shape is the tank chain's.
//!   Large Pe tends to plug flow, small Pe to one well-mixed tank.
//!
//! # Stepping
//!
//! [`Mixer::push`] pushes a volume of one composition in and returns the volume-weighted
//! composition of what left the nozzle meanwhile. Within a push the inflow is constant,
//! and the tanks are advanced by the exact solution of the chain for a constant inflow
//! (the deviation from the inflow in tank i after x = v/(V_t/N) is
//! Σ_{j≤i} d_j·e^(−x)·x^(i−j)/(i−j)!), so the result does not depend on how a volume is
//! split into pushes, and what goes in comes out or stays in the chamber, exactly up to
//! rounding.

use std::collections::VecDeque;

pub mod fit;
pub mod inverse;

use serde::{Deserialize, Serialize};

/// Most tanks a dispersion chamber is modelled with (its mean and variance stay exact;
/// beyond this its shape is a little wider-tailed than the dispersion model's).
pub const MAX_TANKS: usize = 64;

/// The residence-time distribution of a mixing chamber.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MixerModel {
    /// Plug flow: a pure delay of V.
    #[default]
    Plug,
    /// One well-mixed tank: exponential washout.
    Mixed,
    /// Plug flow with axial dispersion (needs a Peclet number).
    Dispersion,
}

impl MixerModel {
    /// The model of a name: `plug`, `mixed` or `dispersion`.
    pub fn from_name(name: &str) -> Result<Self, MixerError> {
        match name {
            "plug" => Ok(MixerModel::Plug),
            "mixed" => Ok(MixerModel::Mixed),
            "dispersion" => Ok(MixerModel::Dispersion),
            other => Err(MixerError::new(
                "model",
                format!("unknown mixer model {other:?}; use plug, mixed or dispersion"),
            )),
        }
    }

    /// The model's name as [`MixerModel::from_name`] reads it.
    pub fn name(self) -> &'static str {
        match self {
            MixerModel::Plug => "plug",
            MixerModel::Mixed => "mixed",
            MixerModel::Dispersion => "dispersion",
        }
    }
}

/// A bad mixer setting, naming its key (`model`, `volume_nl`, `peclet`).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{key}: {message}")]
pub struct MixerError {
    pub key: &'static str,
    pub message: String,
}

impl MixerError {
    fn new(key: &'static str, message: String) -> Self {
        MixerError { key, message }
    }

    /// The command-line option of the key (`--mixer`, `--mixer-volume-nl`,
    /// `--mixer-peclet`: hil-sim's, `edoctl plan`'s and `edoctl demo`'s).
    pub fn option(&self) -> String {
        match self.key {
            "model" => "--mixer".to_string(),
            key => format!("--mixer-{}", key.replace('_', "-")),
        }
    }
}

/// A mixing chamber's description. Build with [`MixerOptions::new`] (validated).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MixerOptions {
    pub model: MixerModel,
    /// Volume of the chamber V, nl (0: no chamber).
    pub volume_nl: f64,
    /// Peclet number Pe (dispersion only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peclet: Option<f64>,
}

impl Default for MixerOptions {
    fn default() -> Self {
        MixerOptions::plug(0.0)
    }
}

impl MixerOptions {
    /// A validated description from a model name, a volume and a Peclet number.
    pub fn new(model: &str, volume_nl: f64, peclet: Option<f64>) -> Result<Self, MixerError> {
        let o = MixerOptions {
            model: MixerModel::from_name(model)?,
            volume_nl,
            peclet,
        };
        o.validate()?;
        Ok(o)
    }

    /// Plug flow through `volume_nl`.
    pub fn plug(volume_nl: f64) -> Self {
        MixerOptions {
            model: MixerModel::Plug,
            volume_nl,
            peclet: None,
        }
    }

    /// Check the volume (finite, 0 or more) and the Peclet number (positive and finite,
    /// given for `dispersion` and only for it).
    pub fn validate(&self) -> Result<(), MixerError> {
        if !(self.volume_nl.is_finite() && self.volume_nl >= 0.0) {
            return Err(MixerError::new(
                "volume_nl",
                format!("must be a volume of 0 nl or more, got {}", self.volume_nl),
            ));
        }
        match (self.model, self.peclet) {
            (MixerModel::Dispersion, None) => Err(MixerError::new(
                "peclet",
                "the dispersion model needs a Peclet number".into(),
            )),
            (MixerModel::Dispersion, Some(pe)) if !(pe.is_finite() && pe > 0.0) => Err(
                MixerError::new("peclet", format!("must be a positive number, got {pe}")),
            ),
            (MixerModel::Plug | MixerModel::Mixed, Some(_)) => Err(MixerError::new(
                "peclet",
                format!(
                    "only the dispersion model takes a Peclet number, not {}",
                    self.model.name()
                ),
            )),
            _ => Ok(()),
        }
    }

    /// The closed form of the residence volume's mean and variance (nl, nl²).
    pub fn residence_moments(&self) -> (f64, f64) {
        let v = self.volume_nl;
        (v, v * v * self.dimensionless_variance())
    }

    /// σ²θ: the residence volume's variance over V².
    fn dimensionless_variance(&self) -> f64 {
        match self.model {
            MixerModel::Plug => 0.0,
            MixerModel::Mixed => 1.0,
            MixerModel::Dispersion => dispersion_variance(self.peclet.unwrap_or(f64::INFINITY)),
        }
    }

    /// The chamber as a plug section and a tank chain: (V_p, N, V_t).
    fn layout(&self) -> (f64, usize, f64) {
        let v = self.volume_nl.max(0.0);
        let s2 = self.dimensionless_variance();
        if !(v > 0.0 && s2 > 0.0) {
            return (v, 0, 0.0);
        }
        let n = ((1.0 / s2).floor() as usize).clamp(1, MAX_TANKS);
        let tanks = (v * (n as f64 * s2).sqrt()).min(v);
        (v - tanks, n, tanks)
    }
}

/// σ²θ of the closed–closed dispersion model, 2/Pe − 2/Pe²·(1 − e^(−Pe)), in (0, 1).
pub fn dispersion_variance(peclet: f64) -> f64 {
    if peclet.is_nan() || peclet <= 0.0 {
        return 1.0;
    }
    if peclet.is_infinite() {
        return 0.0;
    }
    let pe = peclet;
    (2.0 / pe - 2.0 * (-(-pe).exp_m1()) / (pe * pe)).clamp(0.0, 1.0)
}

/// A mixing chamber's state: what it holds, from inlet to nozzle.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mixer {
    /// The plug section from nozzle side (front) to inlet (back): (volume nl,
    /// composition).
    plug: VecDeque<(f64, Vec<f64>)>,
    /// Its volume V_p, nl.
    plug_nl: f64,
    /// The tanks' compositions, the one after the plug section first, the one at the
    /// nozzle last.
    tanks: Vec<Vec<f64>>,
    /// Volume of one tank, nl.
    tank_nl: f64,
}

impl Mixer {
    /// A chamber described by `options`, full of `initial`.
    pub fn new(options: &MixerOptions, initial: &[f64]) -> Self {
        let (plug_nl, n, tanks_nl) = options.layout();
        let mut plug = VecDeque::new();
        if plug_nl > 0.0 {
            plug.push_back((plug_nl, initial.to_vec()));
        }
        Mixer {
            plug,
            plug_nl,
            tanks: vec![initial.to_vec(); n],
            tank_nl: if n > 0 { tanks_nl / n as f64 } else { 0.0 },
        }
    }

    /// Whether the chamber holds nothing (volume 0: what goes in leaves at once).
    pub fn is_empty(&self) -> bool {
        self.plug_nl <= 0.0 && self.tanks.is_empty()
    }

    /// Push `volume_nl` of `inflow` in; the volume-weighted composition of what left
    /// the nozzle meanwhile (`None` when nothing was pushed).
    pub fn push(&mut self, volume_nl: f64, inflow: &[f64]) -> Option<Vec<f64>> {
        if volume_nl.is_nan() || volume_nl <= 0.0 {
            return None;
        }
        if self.is_empty() {
            return Some(inflow.to_vec());
        }
        for t in &mut self.tanks {
            if t.len() < inflow.len() {
                t.resize(inflow.len(), 0.0);
            }
        }
        let mut out = vec![0.0; inflow.len()];
        for (v, c) in self.push_plug(volume_nl, inflow) {
            if self.tanks.is_empty() {
                for (o, x) in out.iter_mut().zip(&c) {
                    *o += v * x;
                }
            } else {
                self.push_tanks(v, &c, &mut out);
            }
        }
        Some(out.iter().map(|x| x / volume_nl).collect())
    }

    /// Push through the plug section: the pieces (volume, composition) that leave it,
    /// in order (the inflow itself when there is no plug section).
    fn push_plug(&mut self, volume_nl: f64, inflow: &[f64]) -> Vec<(f64, Vec<f64>)> {
        if self.plug_nl <= 0.0 {
            return vec![(volume_nl, inflow.to_vec())];
        }
        self.plug.push_back((volume_nl, inflow.to_vec()));
        let mut need = volume_nl;
        let mut pieces = Vec::new();
        while need > 1e-12 {
            let Some(front) = self.plug.front_mut() else {
                break;
            };
            let take = front.0.min(need);
            pieces.push((take, front.1.clone()));
            front.0 -= take;
            need -= take;
            if front.0 <= 1e-12 {
                self.plug.pop_front();
            }
        }
        pieces
    }

    /// Push `volume_nl` of `inflow` through the tank chain (exact for a constant
    /// inflow); add volume × composition of what left the last tank to `out`.
    fn push_tanks(&mut self, volume_nl: f64, inflow: &[f64], out: &mut [f64]) {
        let x = volume_nl / self.tank_nl;
        let n = self.tanks.len();
        // Poisson weights e^(−x)·x^m/m!, m < n.
        let mut weights = Vec::with_capacity(n);
        let mut w = (-x).exp();
        for m in 0..n {
            if m > 0 {
                w *= x / m as f64;
            }
            weights.push(w);
        }
        for (k, (o, c_in)) in out.iter_mut().zip(inflow).enumerate() {
            let before: Vec<f64> = self.tanks.iter().map(|t| t[k] - c_in).collect();
            let mut sum_before = 0.0;
            let mut sum_after = 0.0;
            for i in 0..n {
                let after: f64 = (0..=i).map(|j| before[j] * weights[i - j]).sum();
                sum_before += before[i];
                sum_after += after;
                self.tanks[i][k] = c_in + after;
            }
            // What left: the inflow, plus the deviation the chain lost.
            *o += volume_nl * c_in + self.tank_nl * (sum_before - sum_after);
        }
    }

    /// What the chamber holds, from the nozzle to the inlet: (volume nl, composition).
    pub fn contents(&self) -> Vec<(f64, Vec<f64>)> {
        let tanks = self.tanks.iter().rev().map(|c| (self.tank_nl, c.clone()));
        tanks.chain(self.plug.iter().cloned()).collect()
    }
}

#[cfg(test)]
mod tests;
