//! The process settings a job plans and streams with on a machine: the job's
//! `[toolpath]` bounded by what the machine is (its syringes, flow limit and mixing
//! chamber). edod plans with them; `edoctl plan --machine` and `edoctl demo` too.

use super::MachineConfig;

/// The machine's syringe of each of `job`'s materials: the one named in
/// `materials.syringes`, else the one of the material's own name; one material per
/// part syringe (`role = "part"`). A machine with a support syringe (`role =
/// "support"`) has it last in the plan's order, after the materials, whether the job
/// builds supports of it or not. Else the error names the materials, the machine's
/// syringes and the fix.
pub fn syringe_of_material(
    job: &crate::job::Job,
    machine: &MachineConfig,
    source_name: &str,
) -> Result<Vec<usize>, String> {
    use super::SyringeRole;
    let syringes: Vec<&str> = machine.syringes.iter().map(|s| s.name.as_str()).collect();
    let part: Vec<&str> = machine
        .syringes
        .iter()
        .filter(|s| s.role == SyringeRole::Part)
        .map(|s| s.name.as_str())
        .collect();
    let support = machine
        .syringes
        .iter()
        .position(|s| s.role == SyringeRole::Support);
    if job.materials.len() != part.len() {
        let besides = support
            .map(|k| format!(" besides its support syringe {}", syringes[k]))
            .unwrap_or_default();
        return Err(format!(
            "{source_name}: {} materials ({}) but the machine has {} syringes ({}){besides}: \
             materials.names must list one material per syringe",
            job.materials.len(),
            job.materials.join(", "),
            part.len(),
            part.join(", ")
        ));
    }
    let mut found = material_syringes(job, &syringes, &part, source_name)?;
    check_support_syringe(job, machine, support, source_name)?;
    found.extend(support);
    Ok(found)
}

/// The part syringe of each material (see [`syringe_of_material`]).
fn material_syringes(
    job: &crate::job::Job,
    syringes: &[&str],
    part: &[&str],
    source_name: &str,
) -> Result<Vec<usize>, String> {
    let wanted = job.syringes.as_ref().unwrap_or(&job.materials);
    let key = if job.syringes.is_some() {
        "materials.syringes"
    } else {
        "materials.names"
    };
    let mut found = Vec::with_capacity(wanted.len());
    for (material, name) in job.materials.iter().zip(wanted) {
        let Some(s) = syringes
            .iter()
            .position(|s| s == name)
            .filter(|_| part.contains(&name.as_str()))
        else {
            let fix = if job.syringes.is_some() {
                "name one of them".to_string()
            } else {
                format!(
                    "name the syringe each material is loaded in, in the order of \
                     materials.names: [materials] syringes = [{}]",
                    part.iter()
                        .map(|s| format!("{s:?}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            };
            let what = if syringes.contains(&name.as_str()) {
                "holds the support ink, not"
            } else {
                "is not"
            };
            return Err(format!(
                "{source_name}: {key}: the machine has no syringe \"{name}\" for material \
                 \"{material}\" (its syringes: {}; \"{name}\" {what} one of them); {fix}",
                part.join(", ")
            ));
        };
        found.push(s);
    }
    Ok(found)
}

/// A job building supports of a syringe needs the machine's support syringe of that
/// name.
fn check_support_syringe(
    job: &crate::job::Job,
    machine: &MachineConfig,
    support: Option<usize>,
    source_name: &str,
) -> Result<(), String> {
    let Some(wanted) = job.support.syringe() else {
        return Ok(());
    };
    match support.map(|k| machine.syringes[k].name.as_str()) {
        Some(name) if name == wanted => Ok(()),
        Some(name) => Err(format!(
            "{source_name}: support.syringe = \"{wanted}\": the machine's support syringe \
             is \"{name}\"; name it, or build supports of the part's materials \
             (support.composition)"
        )),
        None => Err(format!(
            "{source_name}: support.syringe = \"{wanted}\": the machine has no support \
             syringe ([[machine.syringes]] role = \"support\"); load the support ink in \
             one, or build supports of the part's materials (support.composition)"
        )),
    }
}

/// The process settings a job streams with on a machine: the job's nozzle, the
/// machine's syringes, flow limit and mixing-chamber volume. `edoctl demo` plans with
/// the same settings to compare what was built with what edod planned.
pub fn process_settings(
    job: &crate::job::Job,
    machine: &MachineConfig,
    source_name: &str,
) -> Result<crate::pipeline::ProcessSettings, String> {
    let syringe_of = syringe_of_material(job, machine, source_name)?;
    // The job's [toolpath] settings, bounded by what this machine is.
    let mut settings = job.toolpath.clone();
    settings.syringes = Some(machine.syringes.len());
    let identity = syringe_of.iter().enumerate().all(|(m, &s)| m == s);
    settings.syringe_of_material = (!identity).then_some(syringe_of);
    // A job that leaves max_flow_factor at its default gets what the machine allows.
    let default_cap = crate::pipeline::ProcessSettings::default().max_flow_factor;
    settings.max_flow_factor = if settings.max_flow_factor == default_cap {
        machine.max_flow_factor
    } else {
        settings.max_flow_factor.min(machine.max_flow_factor)
    };
    let mixer = machine
        .mixer()
        .map_err(|e| format!("machine.mixer.{}: {}", e.key, e.message))?;
    settings.v_dead_ul = mixer.volume_nl / 1000.0;
    settings.mixer_model = mixer.model;
    settings.mixer_peclet = mixer.peclet;
    // The streamer plans a layer before it knows the next one, so the mixing lead cannot
    // reach across a layer change: unless the job purges at layer changes, alternate the
    // sub-region order so that every layer starts with the composition the previous one
    // ended with (no jump to lead for).
    if settings.purge_xy_mm.is_none() {
        settings.sub_region_order = crate::toolpath::SubRegionOrder::Alternating;
    }
    settings
        .validate()
        .map_err(|e| format!("{source_name}: {e}"))?;
    Ok(settings)
}
