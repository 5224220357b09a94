# Two set-up commands (see README): `make demo` and `make test`.
PY ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

# What the firmware tests need (docs/serial-protocol.md, "Emulated board"): the AVR
# toolchain, the Arduino core and simavr's library. Installed when missing and we are
# root with apt-get (CI); otherwise those tests skip and say why.
AVR_APT := gcc-avr avr-libc binutils-avr arduino-core-avr libsimavr2

.PHONY: demo gui test bench clean avr-deps

$(STAMP): pyproject.toml
	test -d $(VENV) || $(PY) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip
	$(VENV)/bin/pip install --quiet -e '.[test]'   # test = gui + cvxpy + test tools
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/labbench run demo --out sessions

gui: $(STAMP)
	$(VENV)/bin/labbench gui

test: $(STAMP) avr-deps
	QT_QPA_PLATFORM=offscreen $(VENV)/bin/pytest -q

avr-deps:
	@if command -v avr-gcc >/dev/null && [ -f /usr/share/arduino/hardware/arduino/avr/platform.txt ] \
	    && [ -n "$$(ls /usr/lib/libsimavr.so.2 /usr/lib/*/libsimavr.so.2 2>/dev/null)" ]; then \
	  echo "avr-deps: installed"; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
	    --no-install-recommends $(AVR_APT) >/dev/null \
	    || echo "avr-deps: apt-get failed: the firmware tests will skip"; \
	else \
	  echo "avr-deps: not root or no apt-get: the firmware tests will skip (need $(AVR_APT))"; \
	fi

bench: $(STAMP)
	for f in bench/bench_*.py; do $(VENV)/bin/python $$f || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache
