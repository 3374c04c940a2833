"""Platform maths: geodesy and MGRS, terrain AGL, targeting CEP, energy, radio, hop plans, SIDC.

Every figure the platform relies on is computed here, by the same functions the pipeline
uses (AGL and endurance on telemetry, CEP on tracks, MGRS for radio and C2 sinks), and is
checked against the claims ledger (``claims.yaml``) by ``fischer-gateway selftest``.

Modules, one concern each: ``geodesy`` (distance, bearing, UTM zones, MGRS), ``projection``
(transverse Mercator for DEM grids), ``dem`` (``.hgt`` and GeoTIFF tiles), ``terrain``
(``TerrainModel``, AGL and its σ, safety floors), ``targeting`` (RSS σ, CEP), ``energy``
(endurance, solar), ``radio`` (path loss, link margin, camera footprint), ``hopping`` (AD9361
hop plans), ``sidc`` (2525C/D symbol codes), ``claims`` and ``selftest`` (the ledger).
"""

from gateway.domain.claims import ClaimsError, load_claims
from gateway.domain.energy import (
    EnergyProfile,
    EwMode,
    endurance_remaining_min,
    net_power_w,
    solar_w,
)
from gateway.domain.geodesy import (
    MgrsError,
    MgrsRef,
    destination,
    distance_bearing,
    from_mgrs,
    to_mgrs,
    utm_zone,
)
from gateway.domain.hopping import HopPlan, HopPlanError, beats_reactive_jammer, hops_per_second
from gateway.domain.radio import (
    LinkBudget,
    coverage_km2,
    fspl_db,
    received_power_dbm,
    slant_range_m,
)
from gateway.domain.selftest import run_selftest
from gateway.domain.sidc import SymbolCodes, symbol_codes
from gateway.domain.targeting import cep, cep50_m, cep90_m, cep_factor, combined_sigma
from gateway.domain.terrain import (
    AglEstimate,
    DemSource,
    TerrainError,
    TerrainModel,
    agl_from_msl,
    agl_sigma,
    msl_from_agl,
    safe_floor_agl_m,
    safe_floor_msl_m,
)

__all__ = [
    "AglEstimate",
    "ClaimsError",
    "DemSource",
    "EnergyProfile",
    "EwMode",
    "HopPlan",
    "HopPlanError",
    "LinkBudget",
    "MgrsError",
    "MgrsRef",
    "SymbolCodes",
    "TerrainError",
    "TerrainModel",
    "agl_from_msl",
    "agl_sigma",
    "beats_reactive_jammer",
    "cep",
    "cep50_m",
    "cep90_m",
    "cep_factor",
    "combined_sigma",
    "coverage_km2",
    "destination",
    "distance_bearing",
    "endurance_remaining_min",
    "from_mgrs",
    "fspl_db",
    "hops_per_second",
    "load_claims",
    "msl_from_agl",
    "net_power_w",
    "received_power_dbm",
    "run_selftest",
    "safe_floor_agl_m",
    "safe_floor_msl_m",
    "slant_range_m",
    "solar_w",
    "symbol_codes",
    "to_mgrs",
    "utm_zone",
]
