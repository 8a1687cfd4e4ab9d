"""Where the model fails and what is missing: candidate effects ranked, tested and fitted (design §6).

- :func:`diagnose` (``fivecal diagnose``): :class:`Diagnosis` with the ``diagnosis`` table, the verdict
  in sentences and the best spec;
- :func:`calibrate_with_effects` (what ``calibrate(..., base=ErrorModel(effects=[...]))`` and
  ``fivecal calibrate --add-effect SPEC`` run): the effects' amplitudes fitted with the constants;
- :func:`linearised_cross_validated_rms`: a calibration's k-fold cross-validated whitened residual;
- :func:`load_effect_modules` (from :mod:`tasks.machine.effects`): import user effect families
  (``--effect-module mypkg.myeffects``).

See docs/diagnosis.md and docs/user-effects.md.
"""

from tasks.analysis.diagnosis.crossval import linearised_cross_validated_rms
from tasks.analysis.diagnosis.diagnose import Diagnosis, diagnose
from tasks.identification.effect_fit import calibrate_with_effects
from tasks.machine.effects import load_effect_modules

__all__ = ["Diagnosis", "calibrate_with_effects", "diagnose", "linearised_cross_validated_rms", "load_effect_modules"]
