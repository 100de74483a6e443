"""What the vehicle is asked to do and what happens to it: references (attitude and altitude;
horizontal position for a position loop), disturbance pulses, wind (gusts, Dryden turbulence),
payload, initial state (a trimmed start), time span, and the paper's canonical scenarios."""

from ._disturbances import PulseDisturbance as PulseDisturbance
from ._disturbances import no_disturbance as no_disturbance
from ._missions import MISSION_PROFILES as MISSION_PROFILES
from ._missions import mission_reference as mission_reference
from ._paper import PAPER_INITIAL_ATTITUDE as PAPER_INITIAL_ATTITUDE
from ._paper import PROFILES as PROFILES
from ._paper import SCENARIO_KINDS as SCENARIO_KINDS
from ._paper import paper_disturbance as paper_disturbance
from ._paper import paper_reference as paper_reference
from ._paper import paper_scenario as paper_scenario
from ._references import PositionReference as PositionReference
from ._references import Reference as Reference
from ._references import make_position_reference as make_position_reference
from ._references import make_reference as make_reference
from ._references import min_jerk_blend as min_jerk_blend
from ._scenario import Scenario as Scenario
from ._scenario import stack_scenarios as stack_scenarios
from ._trimmed import start_at_trim as start_at_trim
from ._trimmed import trim_conditions as trim_conditions
from ._trimmed import trim_scenario as trim_scenario
from ._wind import KNOT as KNOT
from ._wind import ROUGHNESS_LENGTH as ROUGHNESS_LENGTH
from ._wind import TURBULENCE_INTENSITIES as TURBULENCE_INTENSITIES
from ._wind import W20_KNOTS as W20_KNOTS
from ._wind import Wind as Wind
from ._wind import dryden_amplitudes as dryden_amplitudes
from ._wind import dryden_band_amplitudes as dryden_band_amplitudes
from ._wind import dryden_band_fraction as dryden_band_fraction
from ._wind import dryden_correlation as dryden_correlation
from ._wind import dryden_cumulative as dryden_cumulative
from ._wind import dryden_low_altitude as dryden_low_altitude
from ._wind import dryden_psd as dryden_psd
from ._wind import gust_magnitude as gust_magnitude
from ._wind import mean_wind_speed as mean_wind_speed
from ._wind import mean_wind_velocity as mean_wind_velocity
from ._wind import no_wind as no_wind
from ._wind import turbulence_edges as turbulence_edges
from ._wind import turbulence_grid as turbulence_grid
from ._wind import w20 as w20
