# Two commands on a fresh clone: `make demo` and `make test`. Both create .venv and install.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/tissuefit simulate data_spec/examples/paper_tissue.toml --photons 2000000 --out out/demo --plot
	@echo "wrote out/demo/paper_tissue.json and out/demo/paper_tissue.png"
	$(BIN)/tissuefit simulate data_spec/examples/paper_fluorescence.toml --photons 1000000 --out out/demo --plot
	@echo "wrote out/demo/paper_fluorescence.json and out/demo/paper_fluorescence.png"
	@# 100 000 photons at 128 x 128 took 32 s with compilation on the idle 2-core machine (2026-12-06); warm
	@# renders of the example's own size (256 x 256) take 23-30 s (experiments/render/RESULTS.md).
	$(BIN)/tissuefit render data_spec/examples/paper_lesion_render.toml --out out/demo/render --photons 100000 --width 128 --height 128
	@echo "wrote out/demo/render/paper_lesion_render.{tif,json}, out/demo/render/preview.png and out/demo/render/bands.png"
	@# Last, a fit of a synthetic measurement (data_spec/examples/fit_demo.toml): blood fraction and oxygen
	@# saturation of a mucosa recorded by a model camera (bands shifted, 592 nm dead), fitted back from a wrong start.
	$(BIN)/tissuefit synthesize data_spec/examples/fit_demo.toml --out out/demo/fit --seed 1001 --photons 400000 --max-shift 2 --dead-band 592
	$(BIN)/tissuefit fit out/demo/fit/measured.json --scene data_spec/examples/fit_demo.toml --free blood_fraction,blood_saturation \
		--init blood_fraction=0.05,blood_saturation=0.4 --scale --out out/demo/fit
	@echo "truth: blood_fraction 0.02, blood_saturation 0.7 (data_spec/examples/fit_demo.toml); wrote out/demo/fit/fit.{json,png}"
	@# Last, per-pixel maps of the same measurement (white Monte Carlo model, built once and cached).
	@# The stack was recorded under the endoscope's cone lights: --lighting endoscope corrects each pixel's model for
	@# their oblique incidence and fall-off (the model's lighting tables: about 30-40 s the first time, then cached).
	$(BIN)/tissuefit map out/demo/fit/measured.json --scene data_spec/examples/fit_demo.toml --free blood_fraction,saturation \
		--lighting endoscope --out out/demo/map
	@echo "wrote out/demo/map/maps.{tif,json,png} and out/demo/map/summary.json (truth: blood_fraction 0.02, saturation 0.7)"

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n auto --durations=30

test-slow: $(STAMP)
	$(BIN)/python -m pytest -m slow

bench: $(STAMP)
	$(BIN)/python experiments/throughput/run.py
	$(BIN)/python experiments/bench/run.py

clean:
	rm -rf $(VENV) out
