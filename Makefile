# lidarcam: `make demo` and `make test` are all the set-up a fresh machine needs.
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench docs clean

# pip compiles the dependencies' bytecode; an editable install leaves the project's own to the first import,
# which cannot keep it where writing bytecode is switched off (PYTHONDONTWRITEBYTECODE): compiled here.
$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	$(PY) -m compileall -q estimators geometry
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/lidarcam demo

# Two test processes, one per core (pytest-xdist): 6.5 minutes instead of 9.5 on this 2-core machine.
test: $(STAMP)
	$(PY) -m pytest -n 2

# The documentation site (Sphinx): warnings are errors; the notebooks run at small sizes (cached between builds).
docs: $(STAMP)
	$(PY) -m sphinx -b html -W --keep-going -q docs docs/_build/html
	@echo "open docs/_build/html/index.html"

bench: $(STAMP)
	$(PY) benchmarks/bench_pipeline.py
	$(PY) benchmarks/bench_refinement.py
	$(PY) benchmarks/bench_posterior.py
	$(PY) benchmarks/bench_layout.py
	$(PY) benchmarks/bench_realdata.py
	$(PY) benchmarks/bench_scenes.py
	$(PY) benchmarks/bench_handheld.py
	$(PY) benchmarks/bench_stands.py
	$(PY) benchmarks/bench_range_model.py
	$(PY) benchmarks/bench_range_model_scenes.py
	$(PY) benchmarks/bench_range_model_scenes.py --inject 100
	$(PY) benchmarks/bench_board_edges.py --posterior 40
	$(PY) benchmarks/bench_principal_point.py
	$(PY) benchmarks/bench_corners.py
	$(PY) benchmarks/bench_speed.py
	$(PY) benchmarks/bench_2d.py
	$(PY) benchmarks/bench_2d.py --pattern charuco
	$(PY) benchmarks/bench_2d_honesty.py default 200
	$(PY) benchmarks/bench_2d_honesty.py varied 200
	$(PY) benchmarks/bench_2d_honesty.py mounted 200
	$(PY) benchmarks/bench_2d_honesty.py default 100 --pattern charuco
	$(PY) benchmarks/bench_2d_honesty.py varied 100 --pattern charuco
	$(PY) benchmarks/bench_2d_honesty.py mounted 100 --pattern charuco
	$(PY) benchmarks/bench_charuco.py
	$(VENV)/bin/lidarcam study benchmarks/study_2d_end_to_end.yaml --out bench-out/study_2d_end_to_end
	$(VENV)/bin/lidarcam study benchmarks/study_2d_varied_end_to_end.yaml --out bench-out/study_2d_varied_end_to_end
	$(PY) benchmarks/bench_study.py
	$(PY) benchmarks/bench_bag.py
	$(PY) benchmarks/bench_fuzz.py

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis *.egg-info docs/_build
