"""modelDescription.xml of a reference FMU in FMI 2.0 or FMI 3.0, from its variable table (variables.py)."""
from __future__ import annotations

import hashlib
from xml.sax.saxutils import quoteattr

from hil.fmi.variables import ModelSpec, VariableGroup

FMI_VERSIONS = (2, 3)


def guid(spec: ModelSpec) -> str:
    """A GUID (FMI 2) / instantiation token (FMI 3) that changes whenever the variables or the sources could."""
    text = repr((spec.identifier, spec.constants, spec.groups))
    digest = hashlib.sha256(text.encode()).hexdigest()
    return "{" + f"{digest[:8]}-{digest[8:12]}-{digest[12:16]}-{digest[16:20]}-{digest[20:32]}" + "}"


def _attrs(**values: object) -> str:
    return " ".join(f"{k}={quoteattr(str(v))}" for k, v in values.items() if v not in (None, ""))


def _variability(group: VariableGroup) -> str:
    return {"parameter": "fixed", "independent": "continuous"}.get(group.causality, "continuous")


def fmi2_xml(spec: ModelSpec) -> str:
    """FMI 2.0 co-simulation model description (outputs listed in ModelStructure, as the schema asks)."""
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<fmiModelDescription {_attrs(fmiVersion="2.0", modelName=spec.identifier, guid=guid(spec), description=spec.description, generationTool="trainhil", variableNamingConvention="structured", numberOfEventIndicators=0)}>',
             f'  <CoSimulation {_attrs(modelIdentifier=spec.identifier, canHandleVariableCommunicationStepSize="true", canBeInstantiatedOnlyOncePerProcess="false", canNotUseMemoryManagementFunctions="true")}/>',
             f'  <DefaultExperiment {_attrs(startTime=0.0, stepSize=spec.step_s)}/>',
             "  <ModelVariables>"]
    outputs = []
    for index, (vr, name, group) in enumerate(spec.scalars(), start=1):
        start = "" if group.start is None else f' start="{group.start!r}"'
        lines.append(f'    <ScalarVariable {_attrs(name=name, valueReference=vr, description=_described(group), causality=group.causality, variability=_variability(group))}>'
                     f'<Real{start}/></ScalarVariable>')
        if group.causality == "output":
            outputs.append(index)
    lines.append("  </ModelVariables>")
    lines.append("  <ModelStructure>")
    if outputs:
        lines.append("    <Outputs>" + "".join(f'<Unknown index="{i}"/>' for i in outputs) + "</Outputs>")
        lines.append("    <InitialUnknowns>" + "".join(f'<Unknown index="{i}"/>' for i in outputs) + "</InitialUnknowns>")
    lines += ["  </ModelStructure>", "</fmiModelDescription>", ""]
    return "\n".join(lines)


def fmi3_xml(spec: ModelSpec) -> str:
    """FMI 3.0 co-simulation model description (Float64 scalars, the independent time variable)."""
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<fmiModelDescription {_attrs(fmiVersion="3.0", modelName=spec.identifier, instantiationToken=guid(spec), description=spec.description, generationTool="trainhil", variableNamingConvention="structured")}>',
             f'  <CoSimulation {_attrs(modelIdentifier=spec.identifier, canHandleVariableCommunicationStepSize="true", canBeInstantiatedOnlyOncePerProcess="false")}/>',
             f'  <DefaultExperiment {_attrs(startTime=0.0, stepSize=spec.step_s)}/>',
             "  <ModelVariables>"]
    outputs = []
    for vr, name, group in spec.scalars():
        start = None if group.start is None else repr(group.start)
        lines.append(f'    <Float64 {_attrs(name=name, valueReference=vr, description=_described(group), causality=group.causality, variability=_variability(group), start=start)}/>')
        if group.causality == "output":
            outputs.append(vr)
    lines.append("  </ModelVariables>")
    lines.append("  <ModelStructure>")
    lines += [f'    <Output valueReference="{vr}"/>' for vr in outputs]
    lines += [f'    <InitialUnknown valueReference="{vr}"/>' for vr in outputs]
    lines += ["  </ModelStructure>", "</fmiModelDescription>", ""]
    return "\n".join(lines)


def _described(group: VariableGroup) -> str:
    return f"{group.description} ({group.unit})" if group.unit else group.description


def model_description(spec: ModelSpec, fmi_version: int) -> str:
    """The XML for FMI ``fmi_version`` (2 or 3)."""
    if fmi_version not in FMI_VERSIONS:
        raise ValueError(f"FMI version {fmi_version}: the reference FMUs are built for FMI 2 or 3")
    return fmi2_xml(spec) if fmi_version == 2 else fmi3_xml(spec)
