# vet.mk: Make recipes turning a folder of vet captures into HDR images and pictures.
#
# Include it from your own Makefile after setting (or accept the defaults):
#
#   # the vet command (e.g. .venv/bin/vet)
#   VET      = vet
#   # folder of captures, searched recursively
#   CAPTURES = captures
#   # output folder; mirrors CAPTURES' layout
#   OUT      = out
#   include path/to/vet.mk
#   all: vet-all
#
# then `make -j4` builds, for every capture file CAPTURES/d/a.exr (or .npz) and every
# capture folder CAPTURES/d/x/ (holding capture.exr or capture.npz):
#
#   OUT/d/a.hdr.exr   vet hdr-static (radiance, float32 EXR)
#   OUT/d/a.png       vet tonemap of OUT/d/a.hdr.exr
#   OUT/d/x.hdr.exr, OUT/d/x.png   for the capture folder
#
# Make rebuilds only the outputs older than their capture, and every vet command writes
# atomically, so an interrupted `make -j` never leaves a truncated output that a later
# make would take for finished. The recipes pass --force: Make has decided the target is
# out of date, so replacing it is what is asked (vet refuses to replace files otherwise).
# Targets: vet-all, vet-hdr, vet-png, vet-clean, vet-list.
# Make does not track options: after changing VET_TONEMAP_FLAGS run `make -B vet-png`
# (or use `vet batch`, whose manifest does). Every .exr/.npz under CAPTURES is taken for
# a capture (vet batch instead skips files whose metadata says otherwise); files inside
# capture folders are not. OUT must not lie inside CAPTURES.

VET      ?= vet
CAPTURES ?= captures
OUT      ?= out
# A value set as `CAPTURES = captures   # comment` keeps the spaces before the comment:
# strip them, or every path built from it would hold them.
override VET      := $(strip $(VET))
override CAPTURES := $(strip $(CAPTURES))
override OUT      := $(strip $(OUT))
# Extra options for each command, e.g. VET_TONEMAP_FLAGS = --operator reinhard
VET_HDR_FLAGS     ?=
VET_TONEMAP_FLAGS ?=

# Capture files and capture folders, relative to CAPTURES (hidden files skipped).
_vet_found   := $(patsubst $(CAPTURES)/%,%,$(shell find $(CAPTURES) \( -name '.*' ! -name . -prune \) -o -type f \( -name '*.exr' -o -name '*.npz' \) -print 2>/dev/null))
_vet_in_dirs := $(filter %/capture.exr %/capture.npz,$(_vet_found))
_vet_dirs    := $(patsubst %/,%,$(dir $(_vet_in_dirs)))
_vet_files   := $(filter-out $(addsuffix /%,$(_vet_dirs)),$(_vet_found))

#: Output stems (relative to OUT): d/a for CAPTURES/d/a.exr, d/x for CAPTURES/d/x/.
VET_STEMS := $(sort $(basename $(_vet_files)) $(_vet_dirs))
VET_HDR   := $(addprefix $(OUT)/,$(addsuffix .hdr.exr,$(VET_STEMS)))
VET_PNG   := $(addprefix $(OUT)/,$(addsuffix .png,$(VET_STEMS)))

.PHONY: vet-all vet-hdr vet-png vet-clean vet-list
vet-all: vet-hdr vet-png
vet-hdr: $(VET_HDR)
vet-png: $(VET_PNG)

vet-list:
	@printf '%s\n' $(VET_STEMS)

vet-clean:
	rm -f $(VET_HDR) $(VET_PNG)

# Capture folders first: for CAPTURES/x/capture.exr the file rule below would otherwise
# also match OUT/x/capture.hdr.exr, which is not a target.
$(OUT)/%.hdr.exr: $(CAPTURES)/%/capture.exr
	@mkdir -p $(@D)
	$(VET) hdr-static --force $(VET_HDR_FLAGS) $< -o $@

$(OUT)/%.hdr.exr: $(CAPTURES)/%/capture.npz
	@mkdir -p $(@D)
	$(VET) hdr-static --force $(VET_HDR_FLAGS) $< -o $@

$(OUT)/%.hdr.exr: $(CAPTURES)/%.exr
	@mkdir -p $(@D)
	$(VET) hdr-static --force $(VET_HDR_FLAGS) $< -o $@

$(OUT)/%.hdr.exr: $(CAPTURES)/%.npz
	@mkdir -p $(@D)
	$(VET) hdr-static --force $(VET_HDR_FLAGS) $< -o $@

$(OUT)/%.png: $(OUT)/%.hdr.exr
	$(VET) tonemap --force $(VET_TONEMAP_FLAGS) $< -o $@
