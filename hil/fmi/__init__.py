"""The reference FMUs, built here from the project's own C sources with gcc: the train plant and the consensus law.

``variables`` holds their variable tables, ``model_description`` writes the FMI 2 and FMI 3 XML from them and
``build`` compiles and zips an FMU (``hil fmu build``). Running an FMU is ecu_sim/fmu.py's, for any user's FMU."""
