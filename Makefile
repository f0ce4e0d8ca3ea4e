# needlecli: common tasks. `make help` lists them.
PY ?= python

STUDIES := results/studies

.PHONY: help install demo test bench lint clean seed003

help:
	@echo "make install  - install needlecli with test extras (editable)"
	@echo "make demo     - run the bundled default experiment and write its tables"
	@echo "make test     - run the test suite (what .ci/run runs)"
	@echo "make bench    - speed benchmarks (figures also as ratios against an in-run reference)"
	@echo "make lint     - ruff"
	@echo "make seed003  - seed 003's simulation study: Table 1, Figs. 6-8 (results and tables in $(STUDIES))"
	@echo "make clean    - remove results/ and caches"

install:
	$(PY) -m pip install -e '.[test]'

demo:
	needle simulate configs/default.yaml
	needle evaluate results/default.h5

test:
	$(PY) -m pytest

bench:
	$(PY) benchmarks/bench_simulate.py

lint:
	$(PY) -m ruff check needlecli tests benchmarks

clean:
	rm -rf results .pytest_cache .ruff_cache .hypothesis

seed003:
	@for c in table1 fig6 fig7 fig8; do \
	  needle simulate configs/seed003/$$c.yaml --out $(STUDIES)/seed003_$$c.h5 --quiet > /dev/null && \
	  needle evaluate $(STUDIES)/seed003_$$c.h5 --out $(STUDIES)/seed003 || exit 1; \
	done
