"""Loading a cached kernel without parsing its LLVM bitcode: the bitcode is parsed only if another library links it.

A kernel in Numba's cache holds its machine code and, beside it, the optimized LLVM bitcode of its whole library
(``CPUCodeLibrary.serialize_using_object_code``), which is there for one purpose: to be linked into a library
compiled later that calls the kernel. Numba's loader (``CPUCodeLibrary._unserialize``) parses that bitcode into a
module on every load and walks it to record its defined symbols (``JitEngine._load_defined_symbols``), although a
run, which only loads, links nothing: in a 1,000-trial run of case B, 11 kernels carry 3 MB of bitcode and parsing
it took 0.14 s of the 0.28 s that loading the kernels takes at the start of the first chunk (loading holds Numba's
compiler lock: the other worker waits). Without the parse, over alternated runs: a 2-trial run of case B 1.00 ->
0.70 s (6 pairs; the parsed modules were also freed at exit), 1,000 trials 5.77 -> 5.51 s (5 pairs).

:func:`install` replaces the loader for the object-code kind: it keeps the bitcode's bytes and does everything
else as Numba does (the machine code handed to the JIT engine, the library finalized). The bitcode is parsed,
and its symbols recorded, the first time the library is asked for a module to link (``_get_module_for_linking``,
Numba's only reader of it) or for a symbol the engine does not know: a pointer to a function is looked up in the
engine first (the machine code is loaded; MCJIT returns 0 for a name it does not have), and the name recorded as
defined, as Numba's walk would have. A library compiled in this process and the bitcode kind are Numba's code
unchanged.

Nothing is patched if this Numba's loader or its library class does not have the shape this module replaces.
"""

from __future__ import annotations

_PENDING = "_spmc_bitcode"  # the attribute holding a loaded library's unparsed bitcode


def _parse_pending(lib) -> None:
    """Parse ``lib``'s pending bitcode into its shared module and record its symbols (Numba's ``_unserialize``)."""
    bitcode = getattr(lib, _PENDING, None)
    if bitcode is None:
        return
    from numba.core import codegen

    lib._shared_module = codegen.ll.parse_bitcode(bitcode)
    lib._codegen._engine._load_defined_symbols(lib._shared_module)
    setattr(lib, _PENDING, None)


def install() -> bool:
    """Patch Numba's cache loader as described above (once); False if this Numba does not have its shape."""
    from numba.core import codegen

    lib_cls, jit_cls = getattr(codegen, "CPUCodeLibrary", None), getattr(codegen, "JITCodeLibrary", None)
    if lib_cls is None or jit_cls is None:
        return False
    if getattr(lib_cls, "_spmc_lazy", False):
        return True  # installed already
    names = ("_unserialize", "_get_module_for_linking", "enable_object_caching", "_set_compiled_object",
             "_finalize_final_module")  # fmt: skip
    if not all(hasattr(lib_cls, n) for n in names) or not hasattr(jit_cls, "get_pointer_to_function"):
        return False
    numba_unserialize = lib_cls._unserialize.__func__
    numba_linking = lib_cls._get_module_for_linking
    numba_pointer = jit_cls.get_pointer_to_function

    def _unserialize(cls, codegen_, state):
        name, kind, data = state
        if kind != "object":
            return numba_unserialize(cls, codegen_, state)
        object_code, shared_bitcode = data
        self = codegen_.create_library(name)
        assert isinstance(self, cls)
        self.enable_object_caching()
        self._set_compiled_object(object_code)
        setattr(self, _PENDING, shared_bitcode)
        self._finalize_final_module()
        return self

    def _get_module_for_linking(self):
        _parse_pending(self)
        return numba_linking(self)

    def get_pointer_to_function(self, name):
        if getattr(self, _PENDING, None) is not None:
            self._ensure_finalized()
            engine = self._codegen._engine
            if not engine.is_symbol_defined(name):
                address = engine.get_function_address(name)
                if address:
                    engine._defined_symbols.add(name)
                    return address
                _parse_pending(self)
        return numba_pointer(self, name)

    lib_cls._unserialize = classmethod(_unserialize)
    lib_cls._get_module_for_linking = _get_module_for_linking
    jit_cls.get_pointer_to_function = get_pointer_to_function
    lib_cls._spmc_lazy = True
    return True
